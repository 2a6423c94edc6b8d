"""Offscreen rendering of Meta-World episodes and their H.264 videos.

Rendering backend: MuJoCo reads ``MUJOCO_GL`` once, when it is first imported. A value the user
set is kept; otherwise ``egl`` where libEGL is installed, else ``osmesa`` where libOSMesa is
(``choose_backend``). ``check_rendering`` renders one frame in a child process first, so a
missing system library ends the run with one line instead of a traceback from the GL driver.

Frames: one per observation (the first after reset, then one after each action, so an episode
of ``T`` steps gives ``T + 1`` frames), square, upright (Meta-World's corner cameras look
upside down; their frames are turned by 180°), without shadows and reflections (Meta-World's
4096² shadow map makes a 224-px frame about 10× slower on Mesa's software renderer,
llvmpipe). Each frame carries a border
in the episode's outcome colour, green for a success and red for a failure, from its first
frame. Layout ``grid`` tiles the filmed episodes of a task in one video (in episode order, row
by row); a tile whose episode has ended holds its last frame. Layout ``episodes`` writes one
video per episode. Frames stay in memory until the episode's outcome is known: 150 kB a frame
at 224 px, 75 MB for a 500-step episode.
"""

from __future__ import annotations

import ctypes.util
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

BACKENDS = {   # MUJOCO_GL value: (the library ctypes loads, the Debian/Ubuntu packages that bring it)
    "egl": ("EGL", "libegl1 libopengl0 libgl1-mesa-dri"),
    "osmesa": ("OSMesa", "libosmesa6"),
}
INSTALL_HINT = ("EGL needs the Debian/Ubuntu packages " + BACKENDS["egl"][1] + ", OSMesa needs "
                + BACKENDS["osmesa"][1] + " (then MUJOCO_GL=osmesa)")
GREEN, RED = (40, 200, 60), (220, 30, 30)
_PROBE = """
import os, warnings
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    try:
        import mujoco
        renderer = mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 16, 16)
        renderer.render()
        getattr(renderer, "close", lambda: None)()      # mujoco < 3.1 has no close
        error = None
    except Exception as err:
        error = f"{type(err).__name__}: {err}".splitlines()[0]
if error:
    print(([str(w.message) for w in caught] + [error])[0], flush=True)
os._exit(1 if error else 0)   # no interpreter teardown: a half-made GL context prints tracebacks there
"""


def close_renderer(renderer) -> None:
    """Free a `mujoco.Renderer`'s GL contexts now (one left to interpreter exit prints an EGL
    traceback there). mujoco >= 3.1 has `Renderer.close`; older releases are freed by their parts."""
    close = getattr(renderer, "close", None)
    if close is not None:
        close()
        return
    for part in ("_mjr_context", "_gl_context"):
        context = getattr(renderer, part, None)
        if context is not None:
            context.free()
            setattr(renderer, part, None)


def choose_backend(environ=os.environ, find_library=ctypes.util.find_library) -> str:
    """``MUJOCO_GL`` for offscreen rendering: the user's own value, else ``egl`` where libEGL is
    installed, else ``osmesa`` where libOSMesa is; a chosen value is written to ``environ``."""
    if environ.get("MUJOCO_GL"):
        return environ["MUJOCO_GL"].strip().lower()
    if "mujoco" in sys.modules:
        raise ValueError("--video: mujoco was imported before MUJOCO_GL was set, so it cannot render "
                         "offscreen; set MUJOCO_GL=egl (or osmesa) in the environment")
    for backend, (library, _) in BACKENDS.items():
        if find_library(library):
            environ["MUJOCO_GL"] = backend
            return backend
    raise ValueError(f"--video: offscreen rendering needs libEGL or libOSMesa, and neither is installed; "
                     f"{INSTALL_HINT}")


def check_rendering() -> str:
    """Pick the backend and render one frame with it in a child process; returns ``MUJOCO_GL``.

    Raises ValueError with one line when rendering or mp4 writing is unavailable."""
    backend = choose_backend()
    library = BACKENDS.get(backend, (None,))[0]
    if library and not ctypes.util.find_library(library):
        raise ValueError(f"--video: MUJOCO_GL={backend} needs lib{library}, which is not installed; {INSTALL_HINT}")
    probe = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=300)
    if probe.returncode != 0:
        detail = (probe.stdout.strip() or probe.stderr.strip() or f"exit status {probe.returncode}").splitlines()[-1]
        raise ValueError(f"--video: offscreen rendering is unavailable with MUJOCO_GL={backend} ({detail}); "
                         f"{INSTALL_HINT}; glfw needs a display")
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as err:
        raise ValueError(f"--video: writing mp4 needs imageio-ffmpeg and its ffmpeg ({err}): "
                         f"pip install imageio-ffmpeg") from None
    return backend


def make_renderer(model, camera: str, size: int, field: str = "cameras") -> tuple:
    """(model, `mujoco.Renderer` of ``size``², camera id) for the named camera of ``model``;
    a camera the model lacks is one line naming ``field`` and the model's cameras."""
    import mujoco

    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if cam < 0:
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
        raise ValueError(f"{field}: expected one of {', '.join(names)}, got {camera!r}")
    glob, quality = model.vis.global_, model.vis.quality
    kept = glob.offwidth, glob.offheight, quality.offsamples
    # The offscreen buffer is sized (and multisampled) when the context is made; the model keeps its own.
    glob.offwidth, glob.offheight = max(glob.offwidth, size), max(glob.offheight, size)
    quality.offsamples = 0
    try:
        renderer = mujoco.Renderer(model, size, size)
    finally:
        glob.offwidth, glob.offheight, quality.offsamples = kept
    return model, renderer, cam


def render_frame(env_unwrapped, renderer, cam: int) -> np.ndarray:
    """One upright frame [S, S, 3] uint8 of the env's current state, without shadows and reflections."""
    import mujoco

    renderer.update_scene(env_unwrapped.data, camera=cam)
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    frame = renderer.render()                                                # [S, S, 3]
    if env_unwrapped.data.cam_xmat[cam].reshape(3, 3)[2, 1] < 0:            # the image's up axis points down
        frame = np.ascontiguousarray(frame[::-1, ::-1])
    return frame


class CameraObservation:
    """Camera observations of a Meta-World env: ``rig(env) -> {camera: frame [S, S, 3] uint8}``
    for the named cameras (Meta-World names: corner, corner2, topview, …), one renderer per
    (model, camera), upright, no shadows. ``close()`` frees the GL contexts. Call
    `check_rendering()` before the first env is made: ``MUJOCO_GL`` binds when mujoco is imported."""

    def __init__(self, cameras, size: int, field: str = "cameras"):
        if isinstance(cameras, str) or not cameras or not all(isinstance(c, str) and c for c in cameras):
            raise ValueError(f"{field}: expected a non-empty list of camera names, got {cameras!r}")
        if isinstance(size, bool) or not isinstance(size, int) or size < 8:
            raise ValueError(f"{field}: expected an image size of at least 8 pixels, got {size!r}")
        self.cameras, self.size, self.field = list(cameras), size, field
        self._renderers: dict[tuple, tuple] = {}      # (id(model), camera) -> (model, renderer, camera id)

    def __call__(self, env) -> dict[str, np.ndarray]:
        u = env.unwrapped
        frames = {}
        for camera in self.cameras:
            key = (id(u.model), camera)
            if key not in self._renderers:
                self._renderers[key] = make_renderer(u.model, camera, self.size, self.field)
            frames[camera] = render_frame(u, *self._renderers[key][1:])
        return frames

    def close(self) -> None:
        """Free the GL contexts (one left to interpreter exit prints an EGL traceback there)."""
        for _, renderer, _ in self._renderers.values():
            close_renderer(renderer)
        self._renderers.clear()


class EpisodeCamera:
    """The ``on_step(episode, env)`` hook of ``envs.evaluate``: keeps frames ``[S, S, 3]`` uint8 of
    episodes ``0 .. episodes - 1`` from the named camera of each env's own model."""

    def __init__(self, episodes: int, size: int, camera: str):
        self.episodes, self.size, self.camera = episodes, size, camera
        self.frames: dict[int, list[np.ndarray]] = {}
        self.control_dt: float | None = None          # seconds per env step
        self._renderers: dict[tuple, tuple] = {}      # (id(model), camera) -> (model, renderer, camera id)

    def __call__(self, episode: int, env) -> None:
        if episode >= self.episodes:
            return
        u = env.unwrapped
        self.control_dt = float(u.dt)
        key = (id(u.model), self.camera)
        if key not in self._renderers:
            self._renderers[key] = make_renderer(u.model, self.camera, self.size, "--video-camera")
        self.frames.setdefault(episode, []).append(render_frame(u, *self._renderers[key][1:]))

    def close(self) -> None:
        """Free the GL contexts (one left to interpreter exit prints an EGL traceback there)."""
        for _, renderer, _ in self._renderers.values():
            close_renderer(renderer)
        self._renderers.clear()

    def write(self, successes: list[bool], layout: str, fps: float, directory: Path, prefix: str) -> list[Path]:
        """Encode the filmed episodes: ``<prefix>.mp4`` (grid) or ``<prefix>_episode<j+1>.mp4`` (episodes)."""
        if not self.frames:
            return []
        fps = fps or round(1.0 / self.control_dt)
        marked = {ep: framed(np.stack(f), successes[ep]) for ep, f in sorted(self.frames.items())}
        if layout == "grid":
            return [write_mp4(tile(list(marked.values())), directory / f"{prefix}.mp4", fps)]
        return [write_mp4(f, directory / f"{prefix}_episode{ep + 1}.mp4", fps) for ep, f in marked.items()]


def framed(frames: np.ndarray, success: bool) -> np.ndarray:
    """Frames ``[T, S, S, 3]`` with a border of width S/32 (at least 2 px) in the outcome's colour."""
    out, width = frames.copy(), max(2, frames.shape[1] // 32)
    color = np.array(GREEN if success else RED, dtype=np.uint8)
    out[:, :width], out[:, -width:], out[:, :, :width], out[:, :, -width:] = color, color, color, color
    return out


def tile(episodes: list[np.ndarray]) -> np.ndarray:
    """Episodes ``[T_i, S, S, 3]`` as one video ``[max T_i, rows·S, cols·S, 3]``: ceil(√n) columns,
    row by row; an ended episode holds its last frame, and empty cells stay black."""
    n, (size, width) = len(episodes), episodes[0].shape[1:3]
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    grid = np.zeros((max(len(e) for e in episodes), rows * size, cols * width, 3), dtype=np.uint8)
    for i, frames in enumerate(episodes):
        r, c = divmod(i, cols)
        cell = grid[:, r * size:(r + 1) * size, c * width:(c + 1) * width]
        cell[:len(frames)], cell[len(frames):] = frames, frames[-1]
    return grid


def write_mp4(frames: np.ndarray, path: Path, fps: float) -> Path:
    """H.264 (yuv420p, what browsers and players decode) from frames ``[T, H, W, 3]`` uint8."""
    import imageio.v2 as imageio

    with imageio.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264", pixelformat="yuv420p",
                            macro_block_size=16, ffmpeg_log_level="error") as writer:
        for frame in frames:
            writer.append_data(frame)
    return path
