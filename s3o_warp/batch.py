"""Many fits on Ray: ``s3o-batch INPUTS --out RUNS [--address ADDR] ...``.

Each sequence is one Ray task that runs the ordinary fit (:func:`s3o_warp.fit.fit`) into ``RUNS/<name>/``. With no
address Ray starts in this process on this machine; ``--address auto``, ``HOST:PORT`` or ``ray://HOST:PORT`` joins an
existing cluster, which runs the same tasks (INPUTS and RUNS must then be paths every node sees).

INPUTS is one of:

* a folder of sequence folders (each with ``images/`` and ``masks/``), or one sequence folder;
* a DAVIS root with ``--names cows dog ...``;
* a CSV or JSON manifest, one row per object: ``path`` (required; relative to the manifest's folder), ``masks``
  (a mask folder), ``name`` (the sequence inside a DAVIS root), ``run`` (the run folder's name; default the
  sequence's), and any setting as a dotted key (``motion.steps``) that applies to that row only. A row may name
  several videos of one object, fitted together as ``s3o-fit A B ...`` fits them: in JSON a list of paths (and
  ``masks`` a list as long, or none), in CSV the paths in one cell separated by ``;`` (and ``masks`` likewise); its
  run folder's name defaults to the videos' names joined by ``+``.

Every input is checked before Ray starts (paths, manifest rows, settings through
:func:`s3o_warp.config.make_config`): bad input is one line and exit code 2. A fit that fails (bad frames or masks,
a NaN stop) is reported in its row and the others go on; a worker that dies is retried ``--retries`` times, each
retry resuming from the fit's checkpoint. Ctrl-C (or SIGTERM) stops every running fit at its next step with a
checkpoint. Each task appends to ``RUNS/<name>/batch.jsonl`` (one record when an attempt starts, one with the row
when it ends) and the fit's log messages to ``RUNS/<name>/batch.log``; a sequence whose last record says
``finished`` is not run again, so re-running the same command resumes the rest and rewrites nothing in a finished
run. ``RUNS/summary.csv`` and ``RUNS/summary.json`` hold one row per sequence (:data:`COLUMNS`).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import io
import json
import logging
import math
import os
import signal
import socket
import sys
import threading
import time
import traceback
import uuid
from pathlib import Path

import torch
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from s3o_warp.config import PRESETS, Config, make_config
from s3o_warp.data.io import read_json, write_json, write_text
from s3o_warp.errors import InputError
from s3o_warp.fit import FitInterrupted, check_writable, fit, resolve_device
from s3o_warp.run.checkpoint import latest_checkpoint

log = logging.getLogger(__name__)

PROG = "s3o-batch"

COLUMNS = ("name", "status", "wall_s", "fit_s", "device", "node", "attempts", "frames", "bones", "mask_iou", "pck_t",
           "chamfer", "fscore", "joint_distance", "run", "error")
"""The columns of ``summary.csv``. ``status``: finished, failed (the fit raised: bad input, a NaN stop, a bug),
crashed (its worker died on every try), interrupted (stopped with a checkpoint), not started, or running (in the
summary written while the batch runs, after each fit). ``wall_s``: this
attempt's seconds in its task; ``fit_s``: the fit's own clock over all its attempts. ``pck_t`` needs keypoints,
``chamfer``, ``fscore`` (at 2 % of the diagonal) and ``joint_distance`` need ground truth (synthetic sequences).
``summary.json`` has the same rows, plus ``reused`` (finished by an earlier batch) and a failed fit's traceback
when the error was not bad input."""

MANIFEST_KEYS = ("path", "masks", "name", "run")
"""Manifest columns besides settings (dotted keys such as ``motion.steps``)."""

LOG_NAME = "batch.jsonl"
"""Per run: a record when a batch task starts on it and one with its row when the task ends."""
FIT_LOG = "batch.log"
"""Per run: the fit's log messages (the workers' own output stays out of the terminal)."""

STOP_GRACE_S = 600
"""After Ctrl-C, how long the driver waits for the running fits to reach a step boundary and checkpoint; a second
Ctrl-C stops waiting."""


@dataclasses.dataclass
class Item:
    """One sequence of the batch: what the fit is given and where its run goes (``RUNS/<run>``)."""

    run: str
    path: str | tuple[str, ...]
    """The sequence, or several videos of one object (fitted together)."""
    masks: str | tuple[str, ...] | None = None
    name: str | None = None
    settings: tuple[str, ...] = ()
    where: str = ""
    """Where the item came from (manifest row or folder), for error messages."""


# ---------------------------------------------------------------------------------------------------
# Inputs: the batch's items, every one checked before Ray starts
# ---------------------------------------------------------------------------------------------------


def _manifest_rows(path: Path) -> list[tuple[str, dict]]:
    """(where, row) of a CSV or JSON manifest; empty CSV cells are dropped."""
    if path.suffix.lower() == ".json":
        doc = read_json(path, "manifest", "pass a JSON list of objects with a 'path' each")
        if not isinstance(doc, list) or not all(isinstance(r, dict) for r in doc):
            raise InputError(f"{path}: a JSON manifest must be a list of objects like {{\"path\": \"seq\"}}; fix the file")
        return [(f"{path} row {i + 1}", {k: v for k, v in r.items() if v is not None}) for i, r in enumerate(doc)]
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"{path}: cannot read the CSV manifest ({e}); pass a UTF-8 CSV with a 'path' column") from None
    # row 1 is the header
    return [(f"{path} row {i + 2}", {k: v for k, v in r.items() if k is not None and v not in (None, "")})
            for i, r in enumerate(rows)]


def _cell_list(value, where: str, column: str) -> list[str]:
    """A manifest cell as a list of paths: a JSON list, or a string with ``;`` between paths."""
    vals = value if isinstance(value, list) else str(value).split(";")
    vals = [str(v).strip() for v in vals]
    if not vals or any(not v for v in vals):
        raise InputError(f"{where}: an empty entry in {column!r} ({value!r}); give one path per video, separated "
                         "by ';' in a CSV cell")
    return vals


def _relative(p: str, manifest: Path) -> Path:
    """A manifest's path: absolute as given, or relative to the manifest's folder."""
    q = Path(p).expanduser()
    return q if q.is_absolute() else manifest.parent / q


def _manifest_items(path: Path) -> list[Item]:
    items = []
    for where, row in _manifest_rows(path):
        unknown = [k for k in row if k not in MANIFEST_KEYS and "." not in k and k != "seed"]
        if unknown:
            raise InputError(f"{where}: unknown column {unknown[0]!r}; use {', '.join(MANIFEST_KEYS)} or a setting "
                             "such as motion.steps")
        if "path" not in row:
            raise InputError(f"{where}: no path; give each row the sequence folder in the 'path' column")
        seqs = [_relative(p, path) for p in _cell_list(row["path"], where, "path")]
        masks = row.get("masks")
        if masks is not None:
            masks = [str(_relative(m, path)) for m in _cell_list(masks, where, "masks")]
            if len(masks) != len(seqs):
                raise InputError(f"{where}: {len(masks)} mask folder(s) for {len(seqs)} video(s); give one 'masks' "
                                 "entry per path, or none")
        name = str(row["name"]) if "name" in row else None
        if name is not None and len(seqs) > 1:
            raise InputError(f"{where}: 'name' picks one sequence of a DAVIS root, and the row has {len(seqs)} paths; "
                             "give each video its own sequence folder in 'path'")
        settings = tuple(f"{k}={v}" for k, v in row.items() if k not in MANIFEST_KEYS)
        stems = [s.stem if s.is_file() else s.name for s in seqs]
        run = str(row.get("run") or name or "+".join(stems))
        one = len(seqs) == 1
        item_path = str(seqs[0]) if one else tuple(str(s) for s in seqs)
        item_masks = None if masks is None else masks[0] if one else tuple(masks)
        items.append(Item(run=run, path=item_path, masks=item_masks, name=name, settings=settings, where=where))
    if not items:
        raise InputError(f"{path}: the manifest has no rows; add one row per sequence")
    return items


def _davis_items(root: Path, names: list[str]) -> list[Item]:
    frames = root / "JPEGImages"
    known = sorted({p.name for res in frames.iterdir() if res.is_dir() for p in res.iterdir() if p.is_dir()})
    if not names:
        raise InputError(f"{root} is a DAVIS root: pass --names with the sequences to fit, e.g. --names "
                         f"{' '.join(known[:3]) or 'cows'} ({len(known)} there)")
    missing = [n for n in names if n not in known]
    if missing:
        raise InputError(f"--names {missing[0]}: no such sequence under {frames}; pick from {', '.join(known[:20])}")
    return [Item(run=n, path=str(root), name=n, where=f"{root} --names {n}") for n in names]


def collect_items(inputs: str, names: list[str] | None = None) -> list[Item]:
    """The batch's sequences from INPUTS (module docstring); InputError, one line, when INPUTS is none of those."""
    src = Path(inputs).expanduser().absolute()  # workers start elsewhere: every path they get is absolute
    if not src.exists():
        raise InputError(f"{src}: no such file or folder; pass a folder of sequence folders, a DAVIS root or a "
                         "CSV/JSON manifest")
    is_davis = src.is_dir() and (src / "JPEGImages").is_dir()
    if names and not is_davis:
        raise InputError(f"--names picks sequences of a DAVIS root, and {src} has no JPEGImages/; drop --names or "
                         "pass the DAVIS root")
    if src.is_file():
        if src.suffix.lower() not in (".csv", ".json"):
            raise InputError(f"{src}: a manifest must be a .csv or .json file; pass one, or a folder of sequences")
        return _manifest_items(src)
    if is_davis:
        return _davis_items(src, names or [])
    if (src / "images").is_dir():
        return [Item(run=src.name, path=str(src), where=str(src))]
    subs = sorted(p for p in src.iterdir() if p.is_dir() and not p.name.startswith(".") and (p / "images").is_dir())
    if not subs:
        raise InputError(f"{src}: no sequence folders in it (folders with images/ and masks/); pass a folder of them, "
                         "a DAVIS root with --names, or a CSV/JSON manifest")
    return [Item(run=p.name, path=str(p), where=str(p)) for p in subs]


def _as_tuple(v) -> tuple[str, ...]:
    return () if v is None else v if isinstance(v, tuple) else (v,)


def check_items(items: list[Item], preset: str, config: str | None, settings: list[str],
                seed: int | None) -> list[Config]:
    """Every item's paths, run name and settings (the batch's, then its own): one Config per item, or InputError
    naming the item."""
    cfgs, seen = [], {}
    for it in items:
        if not it.run or it.run.startswith(".") or "/" in it.run or "\\" in it.run:
            raise InputError(f"{it.where}: run name {it.run!r} is not a folder name; set the 'run' column to a plain name")
        if it.run in seen:
            raise InputError(f"{it.where}: run name {it.run!r} is also that of {seen[it.run]}; give each row its own "
                             "'run' name")
        seen[it.run] = it.where
        for p in _as_tuple(it.path):
            if not Path(p).exists():
                raise InputError(f"{it.where}: {p} does not exist; fix the path (relative paths start at the "
                                 "manifest's folder)")
        for m in _as_tuple(it.masks):
            if not Path(m).is_dir():
                raise InputError(f"{it.where}: mask folder {m} does not exist; fix the 'masks' column")
        own_seed = [s for s in it.settings if s.startswith("seed=")]
        try:
            cfgs.append(make_config(preset, config, list(settings) + list(it.settings),
                                    None if own_seed else seed))
        except InputError as e:
            raise InputError(f"{it.where}: {e}") from None
        if cfgs[-1].motion.synchronized and not isinstance(it.path, tuple):
            raise InputError(f"{it.where}: motion.synchronized=true needs several videos (the same instants from "
                             "several cameras); list two or more paths in the row, or drop the setting")
    return cfgs


# ---------------------------------------------------------------------------------------------------
# One fit: the Ray task (it runs in a worker process, here or on another node)
# ---------------------------------------------------------------------------------------------------


def _records(run: Path) -> list[dict]:
    """The records of ``run/batch.jsonl`` (a line cut short by a killed worker is skipped)."""
    out = []
    path = run / LOG_NAME
    if path.is_file():
        for line in path.read_text().splitlines():
            with contextlib.suppress(json.JSONDecodeError):
                out.append(json.loads(line))
    return out


def _append(run: Path, rec: dict) -> None:
    with open(run / LOG_NAME, "a") as f:
        f.write(json.dumps(rec) + "\n")


def finished_row(run: Path) -> dict | None:
    """The row of a run a batch finished (its last end record says ``finished``), else None."""
    ends = [r for r in _records(run) if r.get("event") == "end"]
    return ends[-1]["row"] if ends and ends[-1]["row"].get("status") == "finished" else None


def _metric_fields(m: dict) -> dict:
    def get(*keys):
        v = m
        for k in keys:
            v = v.get(k) if isinstance(v, dict) else None
        return v

    if "videos" in m:  # several videos: their mean (frames summed), the fit's own clock
        frames = sum(v.get("frames") or 0 for v in m["videos"].values())
        return {**_metric_fields({**m["mean"], "seconds": m.get("seconds")}), "frames": frames}
    return {"frames": m.get("frames"), "bones": get("bones", "count"), "mask_iou": get("mask_iou", "mean"),
            "pck_t": get("pck_t", "pck"), "chamfer": get("shape_3d", "chamfer"), "fscore": get("shape_3d", "fscore"),
            "joint_distance": get("skeleton", "distance"), "fit_s": m.get("seconds")}


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}".rstrip(": ")


def fit_one(item: Item, cfg: Config, runs: str, batch: str, cpus: float) -> dict:
    """Run one fit into ``runs/<item.run>`` (resuming from its checkpoint when there is one) and return its row.
    The fit's errors become the row's status and error; only a dying worker escapes (Ray retries the task)."""
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # SIGINT is how ray.cancel stops a running task (it interrupts the worker's main thread), also in a worker
        # that inherited it ignored (a cluster started under nohup ... &): the fit checkpoints and stops on it
        signal.signal(signal.SIGINT, signal.default_int_handler)
    run = Path(runs) / item.run
    run.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(max(1, int(cpus)))
    attempt = 1 + sum(1 for r in _records(run) if r.get("event") == "start" and r.get("batch") == batch)
    node = socket.gethostname()
    _append(run, {"event": "start", "batch": batch, "attempt": attempt, "pid": os.getpid(), "node": node,
                  "time": time.time()})
    row = {"name": item.run, "status": "failed", "node": node, "attempts": attempt, "run": str(run)}
    pkg = logging.getLogger("s3o_warp")
    handler = logging.FileHandler(run / FIT_LOG)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    level = pkg.level
    pkg.addHandler(handler)
    pkg.setLevel(logging.INFO)
    t0 = time.perf_counter()
    try:
        pkg.info("batch %s attempt %d on %s (pid %d): %s", batch, attempt, node, os.getpid(), item.path)
        device = resolve_device(None)
        row["device"] = f"{device}, {torch.cuda.get_device_name(device)}" if device.type == "cuda" else \
            f"cpu, {torch.get_num_threads()} torch threads"
        several = isinstance(item.path, tuple)
        metrics = fit(list(item.path) if several else item.path, run, cfg, device,
                      resume=latest_checkpoint(run) is not None,
                      masks=list(item.masks) if several and item.masks is not None else item.masks, name=item.name)
        row.update(_metric_fields(metrics), status="finished")
    except FitInterrupted as e:
        row.update(status="interrupted", error=str(e))
    except KeyboardInterrupt:
        ck = latest_checkpoint(run)
        row.update(status="interrupted", error=f"stopped outside the fit's steps; last checkpoint {ck}")
    except InputError as e:  # bad frames or masks, a NaN stop (FitDiverged): the message is the line
        row.update(error=str(e))
    except Exception as e:  # a bug: its type and first line here, the traceback in summary.json and batch.log
        row.update(error=_one_line(e), traceback=traceback.format_exc())
        pkg.exception("the fit failed")
    finally:
        pkg.removeHandler(handler)
        handler.close()
        pkg.setLevel(level)
    row["wall_s"] = round(time.perf_counter() - t0, 2)
    _append(run, {"event": "end", "batch": batch, "attempt": attempt, "time": time.time(), "row": row})
    return row


# ---------------------------------------------------------------------------------------------------
# The driver: Ray, the tasks, the progress bar and the summary
# ---------------------------------------------------------------------------------------------------


def _import_ray():
    try:
        import ray
    except ImportError:
        raise InputError("Ray is not installed; pip install 's3o-warp[batch]' (or pip install ray)") from None
    return ray


def connect(address: str | None):
    """Join Ray: the running one in this process, else a cluster at ``address``, else a new one on this machine
    with all its CPUs and GPUs. Ray's own logs stay out of the terminal. Returns the module and whether
    this call started the connection (the caller shuts it down)."""
    ray = _import_ray()
    if ray.is_initialized():
        return ray, False
    kw = dict(log_to_driver=False, logging_level=logging.ERROR, include_dashboard=False)
    try:
        if address is None:  # "local": a new instance even when `ray start` left one running here
            ray.init(address="local", **kw)
        else:
            ray.init(address=address, **kw)
    except Exception as e:  # Ray raises ConnectionError, RuntimeError, ValueError... each one line here
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        fix = "start one with `ray start --head` or drop --address" if address else "check `ray status` and Ray's logs"
        raise InputError(f"--address: cannot start or join {where} ({_one_line(e)}); {fix}") from None
    return ray, True


def nodes(ray) -> list[dict]:
    """CPU and GPU counts of the cluster's live nodes."""
    return [{"CPU": n["Resources"].get("CPU", 0), "GPU": n["Resources"].get("GPU", 0)}
            for n in ray.nodes() if n.get("Alive")]


def resources(node_list: list[dict], cpus: float | None, gpus: float | None) -> tuple[float, float]:
    """(CPUs, GPUs) per fit. GPUs default to 1 on a cluster with GPUs, else 0. CPUs default to 1 for a CPU fit (as
    many fits at once as a node has cores: Warp's CPU kernels run on one core and the fit's torch ops are small, so
    two one-core fits on 2 cores end sooner than one two-core fit after another, ``benchmarks/batch-cpu.json``),
    and for a GPU fit to a node's CPUs divided by the fits its GPUs take at once, the smallest such node deciding.
    A request no node can meet is an InputError."""
    if gpus is None:
        gpus = 1.0 if any(n["GPU"] > 0 for n in node_list) else 0.0
    able = [n for n in node_list if n["CPU"] > 0 and n["GPU"] >= gpus]
    if not able:
        most = max((n["GPU"] for n in node_list), default=0)
        raise InputError(f"--gpus-per-fit {gpus:g}: no Ray node has that many GPUs (most: {most:g}); lower it")
    if cpus is None:
        cpus = min(max(1, math.floor(n["CPU"] / math.floor(n["GPU"] / gpus))) for n in able) if gpus > 0 else 1
    if not any(n["CPU"] >= cpus for n in able):
        most = max(n["CPU"] for n in able)
        raise InputError(f"--cpus-per-fit {cpus:g}: no Ray node with {gpus:g} GPUs has that many CPUs (most: "
                         f"{most:g}); lower it")
    return float(cpus), float(gpus)


def _cell(v) -> str:
    """A CSV cell: empty for none, 6 significant digits for a float (summary.json has every digit)."""
    if v is None:
        return ""
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def _summary_rows(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _cell(r.get(k)) for k in COLUMNS})
    return buf.getvalue()


def status_counts(rows: list[dict]) -> dict[str, int]:
    """How many rows have each status."""
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    return counts


def write_summary(runs: Path, rows: list[dict], meta: dict) -> None:
    """``RUNS/summary.csv`` and ``RUNS/summary.json`` (rows in input order), each written atomically."""
    write_json(runs / "summary.json", {**meta, "counts": status_counts(rows), "rows": rows})
    write_text(runs / "summary.csv", _summary_rows(rows))


def _not_run(item: Item, runs: Path, status: str, error: str) -> dict:
    return {"name": item.run, "status": status, "run": str(runs / item.run), "error": error}


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM stops the batch as Ctrl-C does (a handler can only be set in the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handle(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, handle)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _result(ray, ref, item: Item, runs: Path, retries: int) -> dict:
    """The row a finished task gave, or the row of a task that never gave one."""
    try:
        return ray.get(ref)
    except ray.exceptions.TaskCancelledError:
        return _not_run(item, runs, "not started", "the batch was stopped before this fit started; rerun to fit it")
    except ray.exceptions.RayTaskError as e:  # fit_one itself raised (its run folder could not be made...)
        return _not_run(item, runs, "failed", _one_line(e.cause if e.cause is not None else e))
    except ray.exceptions.RayError as e:  # the worker died on every try (killed, out of memory, a crash)
        return _not_run(item, runs, "crashed", f"its worker died on each of {retries + 1} tries ({_one_line(e)}); "
                                               "rerun the command to resume it from its checkpoint")


def _wait(ray, pending: dict, rows: list, items: list[Item], runs: Path, retries: int, bar, on_row) -> bool:
    """Collect the tasks' rows as they end; Ctrl-C asks every running fit to checkpoint and stop, and the rows of
    the stopped fits are still collected (a second Ctrl-C stops waiting). Returns whether the batch was stopped."""
    stopping, deadline = False, math.inf
    while pending:
        try:
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=1.0)
            for ref in ready:
                i = pending.pop(ref)
                rows[i] = _result(ray, ref, items[i], runs, retries)
                bar.update(1)
                bar.set_postfix_str(", ".join(f"{n} {k}" for k, n in status_counts([r for r in rows if r]).items()))
                on_row(rows[i])
            if time.monotonic() > deadline:
                raise KeyboardInterrupt
        except KeyboardInterrupt:
            if stopping:
                for i in pending.values():
                    rows[i] = _not_run(items[i], runs, "interrupted", "the batch stopped before this fit wrote its "
                                                                      "checkpoint; rerun to resume from the last one")
                return True
            stopping, deadline = True, time.monotonic() + STOP_GRACE_S
            log.warning("stopping: %d fits write a checkpoint at their next step (Ctrl-C again to stop waiting)",
                        len(pending))
            for ref in pending:
                ray.cancel(ref, force=False)
    return stopping


def run_batch(items: list[Item], cfgs: list[Config], runs, *, address: str | None = None, cpus: float | None = None,
              gpus: float | None = None, retries: int = 2, meta: dict | None = None,
              progress: bool = True) -> tuple[list[dict], bool]:
    """Fit ``items`` (with their ``cfgs``) into ``runs/<item.run>`` on Ray; return the rows (input order) and
    whether the batch was stopped (Ctrl-C, SIGTERM). Sequences a batch finished earlier are not run again (their
    rows are read back, ``reused``); with nothing left to fit, Ray is not started."""
    runs = Path(runs)
    runs.mkdir(parents=True, exist_ok=True)
    rows: list[dict | None] = [None] * len(items)
    for i, it in enumerate(items):
        done = finished_row(runs / it.run)
        if done is not None:
            rows[i] = {**done, "reused": True}
    todo = [i for i, r in enumerate(rows) if r is None]
    meta = {**(meta or {}), "address": address or "local"}
    t0 = time.perf_counter()

    def on_row(row: dict) -> None:
        if row["status"] != "finished":
            log.warning("%s: %s: %s", row["name"], row["status"], row.get("error"))
        write_summary(runs, [r or _not_run(items[i], runs, "running", None) for i, r in enumerate(rows)],
                      {**meta, "seconds": round(time.perf_counter() - t0, 2)})

    if len(todo) < len(items):
        log.info("%s: %d of %d sequences finished earlier (their rows are kept)", PROG, len(items) - len(todo),
                 len(items))
    stopped = False
    if todo:
        ray, started = connect(address)
        try:
            cpus, gpus = resources(nodes(ray), cpus, gpus)
            meta.update(cpus_per_fit=cpus, gpus_per_fit=gpus)
            log.info("%s: %d fits on Ray (%s), %g CPUs and %g GPUs per fit", PROG, len(todo), meta["address"], cpus,
                     gpus)
            task = ray.remote(fit_one).options(num_cpus=cpus, num_gpus=gpus, max_retries=retries,
                                               retry_exceptions=False)
            batch = uuid.uuid4().hex[:12]
            meta["batch"] = batch
            pending = {task.remote(items[i], cfgs[i], str(runs), batch, cpus): i for i in todo}
            with logging_redirect_tqdm(), tqdm(total=len(items), initial=len(items) - len(todo), desc="batch",
                                               unit="fit", dynamic_ncols=True, disable=not progress) as bar:
                stopped = _wait(ray, pending, rows, items, runs, retries, bar, on_row)
        finally:
            if started:
                ray.shutdown()
    write_summary(runs, rows, {**meta, "seconds": round(time.perf_counter() - t0, 2)})
    return rows, stopped


# ---------------------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description="Fit many sequences on Ray: locally by default, on a cluster "
                                "with --address. Writes RUNS/<name>/ per sequence and RUNS/summary.csv/.json.")
    p.add_argument("inputs", metavar="INPUTS", help="a folder of sequence folders, a DAVIS root with --names, or a "
                   "CSV/JSON manifest (columns path, masks, name, run, and settings such as motion.steps)")
    p.add_argument("--out", required=True, metavar="RUNS", help="folder of the run directories and the summary")
    p.add_argument("--names", nargs="+", default=None, help="sequences of a DAVIS root, e.g. --names cows dog")
    p.add_argument("--address", default=None, help="a Ray cluster to join: auto, HOST:PORT or ray://HOST:PORT "
                   "(default: start Ray on this machine)")
    p.add_argument("--cpus-per-fit", type=float, default=None, help="CPUs each fit reserves (default: 1 for a CPU fit, "
                   "so a node runs a fit per core; with GPUs a node's CPUs shared by the fits its GPUs take)")
    p.add_argument("--gpus-per-fit", type=float, default=None, help="GPUs each fit reserves (default: 1 when the Ray "
                   "cluster has GPUs, else 0)")
    p.add_argument("--retries", type=int, default=2, help="times a fit whose worker died is tried again, each time "
                   "from its checkpoint (default 2)")
    p.add_argument("--preset", default="default", choices=list(PRESETS),
                   help="; ".join(f"{k}: {v[0]}" for k, v in PRESETS.items()))
    p.add_argument("--config", default=None, help="TOML file with settings for every fit (see a run's config.toml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting for every fit, e.g. motion.steps=300 (a manifest row's own win)")
    p.add_argument("--seed", type=int, default=None, help="seed of every fit (a manifest row's seed wins)")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    return p


def _check_flags(args) -> None:
    for flag, v in (("--cpus-per-fit", args.cpus_per_fit), ("--gpus-per-fit", args.gpus_per_fit)):
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise InputError(f"{flag} must be a number >= 0, got {v:g}")
    if args.cpus_per_fit is not None and args.cpus_per_fit <= 0:
        raise InputError(f"--cpus-per-fit must be > 0, got {args.cpus_per_fit:g}; a fit needs a CPU")
    if args.retries < 0:
        raise InputError(f"--retries must be >= 0, got {args.retries}")
    if args.address is not None and not args.address.strip():
        raise InputError("--address is empty; pass auto, HOST:PORT or ray://HOST:PORT, or drop it")


def main(argv: list[str] | None = None) -> int:
    """Exit code: 0 when every fit finished, 1 when some failed or crashed (their rows say why), 2 on bad input
    (nothing started), 130 when stopped (rerun the command to resume)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(message)s")
    try:
        _check_flags(args)
        items = collect_items(args.inputs, args.names)
        cfgs = check_items(items, args.preset, args.config, args.overrides, args.seed)
        runs = Path(args.out).expanduser().absolute()
        check_writable(runs)
        meta = {"command": " ".join([PROG, *(sys.argv[1:] if argv is None else argv)])}
        with _sigterm_as_interrupt():
            rows, stopped = run_batch(items, cfgs, runs, address=args.address, cpus=args.cpus_per_fit,
                                      gpus=args.gpus_per_fit, retries=args.retries, meta=meta)
    except InputError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted before the fits started", file=sys.stderr)
        return 130
    counts = status_counts(rows)
    log.info("%s: %s; summary in %s", PROG, ", ".join(f"{n} {k}" for k, n in counts.items()), runs / "summary.csv")
    if stopped:
        print(f"{PROG}: stopped; the running fits wrote checkpoints: rerun the same command to resume", file=sys.stderr)
        return 130
    return 0 if counts.get("finished", 0) == len(rows) else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
