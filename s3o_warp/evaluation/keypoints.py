"""What each keypoint is, read from its name, and PCK-T counted by those roles.

A fit that is right on the body and wrong on the legs shows it only when PCK-T is split: the limbs' ends (feet,
hooves, paws, hands, wrists, hocks) against the rest, and the side of the body facing the camera against the far
side (the far legs are the ones a side view hides behind the near ones). :func:`keypoint_roles` reads both from
the keypoints' names (BADJA's, the synthetic models' joint names, the built-in quadruped's);
:func:`facing_sides` says, frame by frame, which side faces the camera; :func:`pck_groups` adds up the per-frame,
per-keypoint counts of :func:`s3o_warp.evaluation.image.pck_transfer` into those groups.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

_ENDS = {"foot", "feet", "hand", "paw", "hoof", "hooves", "toe", "toes", "wrist", "ankle", "hock", "finger", "middle",
         "ff", "ffb"}
"""Name tokens of a limb's end (``ff``/``ffb``: the Quaternius models' hoof bones; ``middle``: a middle finger)."""
_LIMB = {"leg", "arm", "forearm", "shin", "calf"}
_LEFT = {"l", "left", "fl", "bl"}
_RIGHT = {"r", "right", "fr", "br"}
_HEAD = {"nose", "head", "jaw", "chin", "snout", "muzzle", "ear", "neck"}
"""Name tokens of the front end (the head and what is next to it), for the side seen in an image."""
_TAIL = {"tail"}
_BADJA_LEG = re.compile(r"^(upper|lower)_(left|right)_(\d)$")
"""BADJA's leg chains (``upper``: the front legs, ``lower``: the hind legs), joints 0 (shoulder, hip) to 3 (paw)."""


def name_tokens(name: str) -> list[str]:
    """A keypoint name's words, lower case: ``"b_LeftHand_011_tip"`` -> ``b left hand 011 tip``,
    ``"FFB.L_tip"`` -> ``ffb l tip``."""
    return [t.lower() for t in re.findall(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+|\d+", name)]


@dataclasses.dataclass(frozen=True)
class KeypointRole:
    """``end``: on a limb's end; ``side``: ``"left"``, ``"right"`` or None (on the body's midline, or unnamed)."""

    end: bool
    side: str | None


def keypoint_role(name: str) -> KeypointRole:
    """The role of one keypoint from its name (see the module's docstring)."""
    m = _BADJA_LEG.match(name)
    if m:  # BADJA: joints 2 and 3 of a leg (wrist or hock, paw) are its end
        return KeypointRole(int(m.group(3)) >= 2, m.group(2))
    words = set(name_tokens(name))
    end = bool(words & _ENDS) or ("tip" in words and bool(words & _LIMB))  # a lower leg's tip: the hoof
    left, right = bool(words & _LEFT), bool(words & _RIGHT)
    return KeypointRole(end, "left" if left and not right else "right" if right and not left else None)


def keypoint_roles(names) -> list[KeypointRole]:
    return [keypoint_role(str(n)) for n in names]


_MIRROR = {"l": "r", "left": "right", "fl": "fr", "bl": "br"}
_MIRROR.update({v: k for k, v in list(_MIRROR.items())})


def counterparts(names) -> list[int | None]:
    """For each keypoint, the index of the same keypoint on the other side of the body (``FF.L_tip`` and
    ``FF.R_tip``, ``upper_left_1`` and ``upper_right_1``, ``paw_fl`` and ``paw_fr``), or None: its words with the side's
    word mirrored (:func:`name_tokens`); where that names none, the same with the numbers left out, when exactly one
    keypoint matches (the Fox's ``b_LeftFoot02_018_tip`` and ``b_RightFoot02_022_tip`` differ in a bone number)."""
    toks = [name_tokens(str(n)) for n in names]
    out: list[int | None] = []
    for i, t in enumerate(toks):
        if not any(w in _MIRROR for w in t):
            out.append(None)
            continue
        want = [_MIRROR.get(w, w) for w in t]
        hits = [j for j, u in enumerate(toks) if j != i and u == want]
        if not hits:
            def bare(ws):
                return [w for w in ws if not w.isdigit()]
            hits = [j for j, u in enumerate(toks) if j != i and bare(u) == bare(want)]
        out.append(hits[0] if len(hits) == 1 else None)
    return out


def facing_sides(names, keypoints: np.ndarray, depth: np.ndarray | None = None) -> list[str | None]:
    """Per annotated frame, the side of the body facing the camera (``"left"``, ``"right"``), or None.

    With ``depth`` (float (A, P) camera-space depth of each keypoint, from a synthetic sequence's ground truth): the
    side whose keypoints are nearer on average, among the keypoints named for a side. Without: from the image, for
    an upright body seen from beside it: the head to the right of the tail shows the body's right side (head and
    tail from the keypoints named so, visible in that frame); None where either is missing or where they are less
    than 5 % of the keypoints' spread apart (a body seen end on).
    """
    roles = keypoint_roles(names)
    kp = np.asarray(keypoints, dtype=np.float64)
    A = kp.shape[0]
    left = np.array([r.side == "left" for r in roles])
    right = np.array([r.side == "right" for r in roles])
    out: list[str | None] = [None] * A
    if not left.any() or not right.any():
        return out
    if depth is not None:
        d = np.asarray(depth, dtype=np.float64)
        for a in range(A):
            dl, dr = d[a, left].mean(), d[a, right].mean()
            out[a] = "left" if dl < dr else "right" if dr < dl else None
        return out
    tok = [set(name_tokens(str(n))) for n in names]
    head = np.array([bool(t & _HEAD) for t in tok])
    tail = np.array([bool(t & _TAIL) for t in tok])
    for a in range(A):
        vis = kp[a, :, 2] > 0.5
        h, t = head & vis, tail & vis
        if not h.any() or not t.any():
            continue
        dx = kp[a, h, 0].mean() - kp[a, t, 0].mean()
        spread = np.ptp(kp[a, vis, :2], axis=0).max() if vis.sum() > 1 else 0.0
        if abs(dx) >= 0.05 * spread and spread > 0:
            out[a] = "right" if dx > 0 else "left"
    return out


def _count(correct: np.ndarray, total: np.ndarray, sel: np.ndarray) -> dict:
    c, t = int(correct[sel].sum()), int(total[sel].sum())
    return {"pck": 100.0 * c / t if t else None, "correct": c, "total": t}


def pck_groups(names, correct: np.ndarray, total: np.ndarray, facing: list[str | None]) -> dict:
    """PCK-T by role: ``ends`` and ``rest`` (each with its ``keypoints``' names), ``near`` and ``far`` (keypoints
    named for a side, counted by whether their side faced the camera in the pair's reference frame; frames where
    no side is known left out), ``ends_near`` and ``ends_far``, ``worst`` (the keypoint of lowest PCK-T with
    ``pck``), and ``frames_with_side`` (the reference frames a side was known in).

    Args:
        names: the P keypoint names.
        correct, total: int (A, P) per reference frame and keypoint, pairs correct and scored
            (:func:`~s3o_warp.evaluation.image.pck_transfer`'s ``per_frame_keypoint_correct`` and ``_total``).
        facing: (A,) the side facing the camera in each reference frame (:func:`facing_sides`).
    """
    roles = keypoint_roles(names)
    c, t = np.asarray(correct), np.asarray(total)
    A, P = t.shape
    end = np.broadcast_to(np.array([r.end for r in roles], bool), (A, P))
    side = np.array([r.side or "" for r in roles])
    known = np.array([f is not None for f in facing], bool)[:, None]
    near = (side[None, :] == np.array([f or "-" for f in facing])[:, None]) & known
    far = (side[None, :] != "") & ~near & known
    out = {
        "ends": {**_count(c, t, end), "keypoints": [str(n) for n, r in zip(names, roles) if r.end]},
        "rest": {**_count(c, t, ~end), "keypoints": [str(n) for n, r in zip(names, roles) if not r.end]},
        "near": _count(c, t, near), "far": _count(c, t, far),
        "ends_near": _count(c, t, near & end), "ends_far": _count(c, t, far & end),
        "frames_with_side": int(known.sum()),
    }
    kc, kt = c.sum(0), t.sum(0)
    scored = np.flatnonzero(kt > 0)
    if scored.size:
        w = scored[np.argmin(kc[scored] / kt[scored])]
        out["worst"] = {"keypoint": str(names[w]), "pck": 100.0 * kc[w] / kt[w]}
    return out
