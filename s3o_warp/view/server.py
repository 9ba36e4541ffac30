"""The page ``s3o-view`` serves: one run directory as a viser scene with a side panel.

Scene (world frame Y up, :mod:`s3o_warp.view.run`):

- the fitted mesh of the current frame: its vertex colours (one GLB node per frame: the first at once, the next few
  with each frame shown, the others in the background once a page has connected, so playing only switches which one
  is shown) or plain shading (one mesh whose vertices are replaced), plain at 35 % opacity ("see-through", which turns
  the skeleton on) or hidden;
- the skeleton of the current frame (off at first: it is inside the mesh): a segment from each joint (red) to the
  centre (blue) of each of its two bones;
- the fitted camera of every frame as a frustum with that frame's picture (the current one orange), and, after "Look
  through the camera", the current frame's picture behind the mesh where that camera sees it (principal point
  included), so the mesh sits on the animal.

Panel: the frame slider, play/pause at the video's frame rate, what is drawn, the run's figures (``metrics.json``) and
its settings (``config.toml``). Every ``poll_s`` seconds the run directory is looked at again: a newer checkpoint (a
fit still running) or a new ``motion.npz`` replaces the scene. A fit of several videos has a "video" selector above
the rest: the video chosen replaces the scene, frames, cameras and figures with its own, as a fit of one shows them.
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
import time
from pathlib import Path

import numpy as np
import viser
import viser.transforms as vtf

from s3o_warp.errors import InputError
from s3o_warp.view.glb import mesh_glb
from s3o_warp.view.run import SURFACES, FitView, figures, frame_image, frame_images, load_view, signature

log = logging.getLogger(__name__)

PLAIN_COLOR = (200, 200, 210)
SEE_THROUGH_OPACITY = 0.35
CAMERA_COLOR = (140, 140, 140)
CURRENT_CAMERA_COLOR = (255, 110, 0)
BONE_COLOR = (255, 200, 0)
JOINT_COLOR = (230, 0, 0)
CENTRE_COLOR = (0, 140, 255)
FRUSTUM_SIZE = 0.1
"""Depth of a drawn camera frustum, as a fraction of the mesh's bounding-box diagonal."""
IMAGE_SIDE = 320
"""Longest side in pixels of the pictures on the frustums."""
FILL_DELAY = 3.0
"""Seconds after the first page connects before the other frames' meshes and the pictures are sent to it."""
FILL_PAUSE = 0.03
"""Seconds between two of them, so that the page draws in between instead of parsing them all first."""
PREFETCH = 3
"""Frames after the one shown whose meshes are sent with it (parsed by the time they are shown)."""
BACKDROP_SIDE = 1280
"""Longest side in pixels of the picture behind the mesh."""
START_VIEW = (40.0, 20.0, 2.2)
"""Where a new page looks from: frame 0's camera direction turned this many degrees about the vertical, raised this
many degrees, at this many mesh diagonals from the mesh's centre."""
HEMISPHERE_LIGHT = 1.6
"""Intensity of the hemisphere light (sky white, ground grey) under viser's default lights."""
START_FOV = 50.0
"""A new page's vertical field of view, degrees."""


class ViewServer:
    """The viser server of one run directory (see the module docstring); :meth:`close` stops it.

    Args:
        run: the run directory.
        host, port: where to listen (port 0: any free port; a busy one: the next free one, as viser does).
        sequence: where the input frames are (default: as :func:`s3o_warp.view.run.find_sequence` finds them).
        surface: the first of :data:`SURFACES` shown.
        plain_color: RGB of the plain surface.
        poll_s: seconds between looks at the run directory (0: never).
        video: of a fit of several videos, the one shown first (a name or an index; default the first); ``sequence``
            is that video's frames.

    Raises:
        InputError: the run cannot be shown (one line naming the file and the fix), before any port is opened.
    """

    def __init__(self, run, host: str = "127.0.0.1", port: int = 8080, sequence=None, surface: str = SURFACES[0],
                 plain_color=PLAIN_COLOR, poll_s: float = 2.0, video=None):
        if surface not in SURFACES:
            raise InputError(f"surface {surface!r}: choose one of {', '.join(SURFACES)}")
        self.run, self.sequence = Path(run), sequence
        self.plain_color = tuple(int(c) for c in plain_color)
        self.view: FitView = load_view(self.run, sequence, video)
        self._sequence_video = self.view.video  # the video that ``sequence`` is the frames of
        self._replacing = False  # the video selector being set to the video shown (not a choice)
        self._signature = signature(self.run)
        self.lock = threading.RLock()
        self.frame = 0
        self.playing = False
        self.generation = 0  # bumped at every rebuild; background work of an older scene stops
        self.images: dict[int, np.ndarray] = {}
        self._handles: list = []
        self._fills: list[threading.Thread] = []  # background loading of each scene built
        self._stop = threading.Event()
        self._client_seen = threading.Event()  # a page has connected: the background loading starts
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner; s3o-view prints the address itself
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.host = host
        self.server.on_client_connect(lambda _: self._client_seen.set())
        self.server.gui.configure_theme(show_share_button=False, control_width="medium")
        self.server.scene.set_up_direction("+y")
        # no environment map (viser's default one costs a page drawn without a GPU about 6 s before it draws): a
        # hemisphere light under viser's default ones lights the sides they leave dark
        self.server.scene.configure_environment_map(hdri=None)
        self.server.scene.add_light_hemisphere("/light", sky_color=(255, 255, 255), ground_color=(110, 105, 100),
                                               intensity=HEMISPHERE_LIGHT)
        self._build_gui(surface)
        self._build_scene()
        self._threads = [threading.Thread(target=self._play_loop, name="s3o-view-play", daemon=True)]
        if poll_s > 0:
            self._threads.append(threading.Thread(target=self._poll_loop, args=(poll_s,), name="s3o-view-poll",
                                                  daemon=True))
        for th in self._threads:
            th.start()

    # ------------------------------------------------------------------------------------------ address
    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = "localhost" if self.host in ("0.0.0.0", "::") else self.host
        return f"http://{host}:{self.port}"

    def close(self) -> None:
        """Stop the background threads (one still reading a checkpoint is left to end with the process) and the
        server."""
        self._stop.set()
        for th in self._threads + self._fills:
            th.join(timeout=2)
        self.server.stop()

    # ---------------------------------------------------------------------------------------------- panel
    def _build_gui(self, surface: str) -> None:
        gui, v = self.server.gui, self.view
        self.video_select = None
        if len(v.videos) > 1:
            self.video_select = gui.add_dropdown("video", tuple(v.videos), initial_value=v.videos[v.video],
                                                 hint="the fit's videos: each one's motion, cameras and figures")
        self.header = gui.add_markdown(self._header_text())
        with gui.add_folder("Playback"):
            self.slider = gui.add_slider("frame", min=0, max=max(v.num_frames - 1, 1), step=1, initial_value=0)
            self.play_button = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
            self.frame_text = gui.add_markdown(self._frame_text(0))
        with gui.add_folder("Show"):
            self.surface = gui.add_dropdown("surface", SURFACES, initial_value=surface)
            self.show_skeleton = gui.add_checkbox("skeleton", surface == "see-through",
                                                  hint="inside the mesh: pick see-through to see it")
            self.show_cameras = gui.add_checkbox("cameras", True)
            self.look_button = gui.add_button("Look through the camera", icon=viser.Icon.CAMERA,
                                              hint="set your view to the fitted camera of this frame")
            self.follow = gui.add_checkbox("follow the camera", False, hint="keep looking through it while playing")
            self.show_backdrop = gui.add_checkbox("frame behind the mesh", False,
                                                  hint="the input frame where the fitted camera sees it")
        with gui.add_folder("Figures"):
            self.figures_text = gui.add_markdown(self._figures_text())
        with gui.add_folder("Settings", expand_by_default=False):
            self.settings_text = gui.add_markdown(self._settings_text())

        if self.video_select is not None:
            self.video_select.on_update(lambda _: self._video_chosen())
        self.slider.on_update(lambda _: self.show_frame(int(self.slider.value)))
        self.play_button.on_click(lambda _: self.set_playing(not self.playing))
        self.surface.on_update(lambda _: self._surface_changed())
        self.show_skeleton.on_update(lambda _: self._apply_visibility())
        self.show_cameras.on_update(lambda _: self._apply_visibility())
        self.show_backdrop.on_update(lambda _: self._update_backdrop())
        self.look_button.on_click(lambda event: self.look_through(event.client))
        self.follow.on_update(lambda _: self._follow())

    def _header_text(self) -> str:
        v = self.view
        which = f", video **{v.videos[v.video]}** ({v.video + 1} of {len(v.videos)})" if len(v.videos) > 1 else ""
        return (f"**{v.run.resolve().name}**{which}: {v.label}, {v.num_frames} frames at {v.fps:g} fps, "
                f"{v.verts.shape[1]} vertices, {v.centres.shape[1]} bones")

    def _frame_text(self, t: int) -> str:
        v = self.view
        return f"frame {t} (`{v.frame_names[t]}`), {t / v.fps:.2f} s"

    def _figures_text(self) -> str:
        rows = figures(self.view.metrics)
        if not rows:
            return "No figures yet (`metrics.json` is written when the fit ends)."
        return "| | |\n|---|---|\n" + "\n".join(f"| {k} | {val} |" for k, val in rows)

    def _settings_text(self) -> str:
        text = self.view.config_text
        return f"```toml\n{text.strip()}\n```" if text else "No `config.toml` in the run directory."

    # ---------------------------------------------------------------------------------------------- scene
    def _build_scene(self) -> None:
        """Add the scene of ``self.view`` (the first frame's mesh now, the others and the pictures in background)."""
        scene, v = self.server.scene, self.view
        t = min(self.frame, v.num_frames - 1)
        self.frame = t
        size = v.size()
        self.generation += 1
        self.images = {}
        self._backdrop_image: tuple = (None, None)  # (frame, picture) behind the mesh
        with self.server.atomic():
            self.colour_root = scene.add_frame("/fit/colour", show_axes=False)
            self.colour_nodes: list = [None] * v.num_frames
            self._colour_node(t)
            self.plain = scene.add_mesh_simple("/fit/plain", v.verts[t], v.faces, color=self.plain_color,
                                               side="double")
            self.skeleton_root = scene.add_frame("/fit/skeleton", show_axes=False)
            self.bones = self.joints = self.centres = None
            if len(v.bone_links):
                self.bones = scene.add_line_segments("/fit/skeleton/bones", v.bone_segments(t), BONE_COLOR,
                                                     thickness=0.006 * size)
            if v.joints.shape[1]:
                self.joints = scene.add_point_cloud("/fit/skeleton/joints", v.joints[t], JOINT_COLOR,
                                                    point_size=0.015 * size, point_shape="circle")
            if v.centres.shape[1]:
                self.centres = scene.add_point_cloud("/fit/skeleton/centres", v.centres[t], CENTRE_COLOR,
                                                     point_size=0.012 * size, point_shape="circle")
            self.cameras_root = scene.add_frame("/cameras", show_axes=False)
            self.frustums: list = [None] * v.num_frames
            self._frustum(t)
            self.backdrop = None
            floor = float(v.verts[..., 1].min())
            c = v.centre()
            self.grid = scene.add_grid("/grid", width=4 * size, height=4 * size, plane="xz", cell_size=0.1 * size,
                                       section_size=0.5 * size, position=(c[0], floor, c[2]))
            self._apply_visibility()
        self._set_initial_camera()
        self._handles = [self.colour_root, self.plain, self.skeleton_root, self.cameras_root, self.grid]
        fill = threading.Thread(target=self._fill_in, args=(self.generation,), name="s3o-view-fill", daemon=True)
        self._fills = [th for th in self._fills if th.is_alive()] + [fill]
        fill.start()

    def _colour_node(self, t: int):
        """The vertex-coloured mesh of frame t (made now if the background has not made it yet)."""
        with self.lock:
            node = self.colour_nodes[t]
            if node is None:
                v = self.view
                node = self.server.scene.add_glb(f"/fit/colour/f{t:05d}", mesh_glb(v.verts[t], v.faces, v.colors),
                                                 visible=t == self.frame)
                self.colour_nodes[t] = node
            return node

    def _frustum(self, k: int):
        """Frame k's camera frustum (made now if the background has not made it yet)."""
        with self.lock:
            node = self.frustums[k]
            if node is None:
                v, c2w = self.view, self.view.cam_to_world[k]
                node = self.server.scene.add_camera_frustum(
                    f"/cameras/f{k:05d}", fov=v.fov_y(k), aspect=v.aspect(k), scale=FRUSTUM_SIZE * v.size(),
                    thickness=0.003 * v.size(), color=CURRENT_CAMERA_COLOR if k == self.frame else CAMERA_COLOR,
                    wxyz=vtf.SO3.from_matrix(c2w[:3, :3]).wxyz, position=c2w[:3, 3], cast_shadow=False,
                    receive_shadow=False)
                if k in self.images:
                    node.image = self.images[k]
                self.frustums[k] = node
            return node

    def _fill_in(self, gen: int) -> None:
        """Background, once a page has connected: every frame's camera and coloured mesh, then the pictures on the
        frustums (sent before the page first draws, they would all be drawn or parsed before it does)."""
        while not self._client_seen.wait(0.1):
            if self._stop.is_set() or gen != self.generation:
                return
        if self._stop.wait(FILL_DELAY):
            return
        try:
            for t in range(self.view.num_frames):
                if self._stop.wait(FILL_PAUSE) or gen != self.generation:
                    return
                self._frustum(t)
                self._colour_node(t)
            for t, img in frame_images(self.view, IMAGE_SIDE):
                if self._stop.wait(FILL_PAUSE) or gen != self.generation:
                    return
                with self.lock:
                    self.images[t] = img
                    self._frustum(t).image = img
                    if t == self.frame:
                        self._update_backdrop()
            log.debug("scene %d filled in", gen)
        except Exception:  # noqa: BLE001 - a background failure is logged; the page stays up
            log.exception("the viewer's background loading failed")

    def _set_initial_camera(self) -> None:
        """New pages look at the mesh from :data:`START_VIEW` beside frame 0's fitted camera (seen from there, the
        cameras' pictures would hide it)."""
        v, cam = self.view, self.server.initial_camera
        c = v.centre()
        d = v.cam_to_world[0][:3, 3] - c
        turn, rise, dist = START_VIEW
        a = np.radians(turn)
        h = np.array([d[0] * np.cos(a) + d[2] * np.sin(a), 0.0, -d[0] * np.sin(a) + d[2] * np.cos(a)])  # about +y
        h = h / max(np.linalg.norm(h), 1e-9)
        e = np.radians(rise)
        direction = h * np.cos(e) + np.array([0.0, 1.0, 0.0]) * np.sin(e)
        cam.fov = np.radians(START_FOV)
        cam.position = tuple(c + direction * dist * v.size())
        cam.look_at = tuple(c)
        cam.up = (0.0, 1.0, 0.0)

    def _surface_changed(self) -> None:
        if self.surface.value == "see-through" and not self.show_skeleton.value:
            self.show_skeleton.value = True  # what see-through is for; -> _apply_visibility
        self._apply_visibility()

    def _apply_visibility(self) -> None:
        with self.lock, self.server.atomic():
            s = self.surface.value
            self.colour_root.visible = s == "colours"
            self.plain.visible = s in ("plain", "see-through")
            self.plain.opacity = SEE_THROUGH_OPACITY if s == "see-through" else None
            self.skeleton_root.visible = bool(self.show_skeleton.value)
            self.cameras_root.visible = bool(self.show_cameras.value)

    # ---------------------------------------------------------------------------------------------- frames
    def show_frame(self, t: int) -> None:
        """Draw frame t: its mesh, skeleton, current camera, picture and the slider's text."""
        v = self.view
        t = int(np.clip(t, 0, v.num_frames - 1))
        with self.lock, self.server.atomic():
            old, self.frame = self.frame, t
            if old != t and old < len(self.colour_nodes) and self.colour_nodes[old] is not None:
                self.colour_nodes[old].visible = False
            self._colour_node(t).visible = True
            for k in range(t + 1, min(t + 1 + PREFETCH, v.num_frames)):
                self._colour_node(k)
            self.plain.vertices = v.verts[t]
            if self.bones is not None:
                self.bones.points = v.bone_segments(t)
            if self.joints is not None:
                self.joints.points = v.joints[t]
            if self.centres is not None:
                self.centres.points = v.centres[t]
            if old != t and old < len(self.frustums) and self.frustums[old] is not None:
                self.frustums[old].color = CAMERA_COLOR
            self._frustum(t).color = CURRENT_CAMERA_COLOR
            self.frame_text.content = self._frame_text(t)
            if int(self.slider.value) != t:
                self.slider.value = t
            self._update_backdrop()
        self._follow()

    def set_playing(self, playing: bool) -> None:
        """Start or pause playback at the video's frame rate."""
        self.playing = bool(playing)
        self.play_button.label = "Pause" if self.playing else "Play"
        self.play_button.icon = viser.Icon.PLAYER_PAUSE if self.playing else viser.Icon.PLAYER_PLAY

    def _play_loop(self) -> None:
        next_at = time.perf_counter()
        while not self._stop.is_set():
            if not self.playing:
                self._stop.wait(0.05)
                next_at = time.perf_counter()
                continue
            next_at += 1.0 / self.view.fps
            self.slider.value = (self.frame + 1) % self.view.num_frames  # -> show_frame
            self._stop.wait(max(0.0, next_at - time.perf_counter()))
            next_at = max(next_at, time.perf_counter() - 0.5)  # a slow frame is dropped, not caught up with

    # ---------------------------------------------------------------------------------------------- camera
    def camera_pose(self, t: int) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """Frame t's fitted camera: (wxyz, position, vertical fov in radians, a point it looks at on the mesh)."""
        v = self.view
        c2w = v.cam_to_world[t]
        near, far = v.depth_range(t)
        look_at = c2w[:3, 3] + c2w[:3, 2] * max(0.5 * (near + far), 1e-3)
        return vtf.SO3.from_matrix(c2w[:3, :3]).wxyz, c2w[:3, 3], v.fov_y(t), look_at

    def look_through(self, client, t: int | None = None) -> None:
        """Set ``client``'s view to the fitted camera of frame t (the current one), show that frame behind the mesh and
        hide the frusta (those around the camera would hide the view)."""
        if client is None:
            return
        wxyz, pos, fov, look_at = self.camera_pose(self.frame if t is None else t)
        with client.atomic():
            client.camera.fov = fov
            client.camera.position = pos
            client.camera.wxyz = wxyz
            client.camera.look_at = look_at
        if not self.show_backdrop.value:
            self.show_backdrop.value = True  # -> _update_backdrop
        if self.show_cameras.value:
            self.show_cameras.value = False  # the frusta around the camera would hide the view

    def _follow(self) -> None:
        if self.follow.value:
            for client in self.server.get_clients().values():
                self.look_through(client)

    def _update_backdrop(self) -> None:
        """The current frame's picture on the plane behind the mesh that its camera sees it on (the floor grid
        hidden meanwhile: it would lie over the picture)."""
        with self.lock:
            v, t = self.view, self.frame
            img = None
            if self.show_backdrop.value:
                if self._backdrop_image[0] != t:
                    self._backdrop_image = (t, frame_image(v, t, BACKDROP_SIDE))
                img = self._backdrop_image[1] if self._backdrop_image[1] is not None else self.images.get(t)
            self.grid.visible = img is None
            if img is None:
                if self.backdrop is not None:
                    self.backdrop.visible = False
                return
            H, W = v.image_size
            K, c2w = v.K[t], v.cam_to_world[t]
            depth = 1.5 * v.depth_range(t)[1]
            # centre of the picture in the camera frame at that depth, and its size there
            centre = np.array([((W - 1) / 2 - K[0, 2]) / K[0, 0], ((H - 1) / 2 - K[1, 2]) / K[1, 1], 1.0]) * depth
            pos = c2w[:3, :3] @ centre + c2w[:3, 3]
            wxyz = vtf.SO3.from_matrix(c2w[:3, :3]).wxyz
            self.backdrop = self.server.scene.add_image("/backdrop", img, render_width=W / K[0, 0] * depth,
                                                        render_height=H / K[1, 1] * depth, wxyz=wxyz, position=pos,
                                                        cast_shadow=False, receive_shadow=False)

    # ---------------------------------------------------------------------------------------------- updates
    def poll(self) -> bool:
        """Look at the run directory again; when something newer is there, show it. Returns whether it did."""
        sig = signature(self.run)
        if sig == self._signature:
            return False
        view = self._load(self.view.video)
        if view is None:
            return False
        self._signature = sig
        log.info("s3o-view: %s changed, now showing %s", self.run, view.label)
        self._replace(view)
        return True

    def show_video(self, video) -> bool:
        """Show video ``video`` (a name or an index) of a fit of several from its first frame. Returns whether it
        did (not when it is the one shown, or cannot be read: a warning says why)."""
        with self.lock:
            v = self.view
            index = video if isinstance(video, int) else v.videos.index(video) if video in v.videos else None
            if index is None or index == v.video:
                return False
            view = self._load(index)
            if view is None:
                return False
            log.info("s3o-view: now showing video %s (%s)", view.videos[view.video] if view.videos else index,
                     view.label)
            self.frame = 0
            self._replace(view)
        return True

    def _video_chosen(self) -> None:
        with self.lock:
            if self._replacing:  # the selector set to what is being shown
                return
            if not self.show_video(str(self.video_select.value)) and self.view.videos:
                self.video_select.value = self.view.videos[self.view.video]  # one that cannot be read: back

    def _load(self, video: int) -> FitView | None:
        """``load_view`` of video ``video`` (``sequence`` where it is the video the server started on), or None
        when it cannot be read (a warning says why: a file half-way through being replaced, say)."""
        seq = self.sequence if video == self._sequence_video else None
        try:
            return load_view(self.run, seq, video)
        except InputError as e:
            log.warning("s3o-view: %s; keeping what is shown", e)
            return None

    def _replace(self, view: FitView) -> None:
        """Show ``view`` in place of the scene, frames, figures and settings shown."""
        with self.lock:
            for h in self._handles:
                h.remove()
            if self.backdrop is not None:
                self.backdrop.remove()
            self.view = view
            if self.video_select is not None and view.videos:
                self._replacing = True
                try:
                    if tuple(view.videos) != tuple(self.video_select.options):  # a running fit's names, then its own
                        self.video_select.options = tuple(view.videos)
                    self.video_select.value = view.videos[view.video]
                finally:
                    self._replacing = False
            self.slider.max = max(view.num_frames - 1, 1)
            self.header.content = self._header_text()
            self.figures_text.content = self._figures_text()
            self.settings_text.content = self._settings_text()
            self._build_scene()
            self.show_frame(self.frame)

    def _poll_loop(self, every: float) -> None:
        while not self._stop.wait(every):
            try:
                self.poll()
            except Exception:  # noqa: BLE001 - the page stays up; the next look tries again
                log.exception("s3o-view: reading %s failed", self.run)
