"""Headless MuJoCo rendering: GL back-end selection and a first-person renderer.

The renderer draws a house model from a camera pose written straight into
``MjData.cam_xpos``/``cam_xmat`` (the agent is kinematic, so no physics step is
needed), with shadows, multisampling and skybox off, into an offscreen buffer of
the frame's size, with bilinear (nearest-mipmap) texture minification: at 64x64
pixels a house (one textured mesh) takes about 0.3 ms a frame on one CPU core with
Mesa llvmpipe (see ``benchmarks/results/env.json``).

The OpenGL context is created lazily, at the first render, so a process that
only reads an environment's specs (a ``ParallelEnv`` parent, a collector
building its buffers) never opens one.

Back-end selection, done once per process before ``mujoco`` opens any context:

* ``MUJOCO_GL`` set by the user is respected as it is;
* otherwise ``egl`` when ``libEGL`` can be loaded (headless, Mesa or a GPU);
* otherwise ``osmesa`` when ``libOSMesa`` can be loaded, with a warning;
* otherwise :class:`RendererUnavailableError` naming the packages to install.
"""
from __future__ import annotations

import atexit
import ctypes
import ctypes.util
import functools
import logging
import math
import os
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from envs.house_mesh import house_model
from envs.scenes import FIELD_OF_VIEW_DEG, House

logger = logging.getLogger(__name__)

#: GL back-ends this project knows how to use headless.
SUPPORTED_GL_BACKENDS = ("egl", "osmesa", "glfw")

_INSTALL_HINT = (
    "Install Mesa's EGL (Debian/Ubuntu: `apt-get install libegl1 libgl1-mesa-dri`) "
    "or OSMesa (`apt-get install libosmesa6`), or set MUJOCO_GL to one of "
    f"{SUPPORTED_GL_BACKENDS}."
)


#: Renderers holding a GL context, closed at interpreter exit: a context left to the
#: garbage collector during interpreter teardown fails to free (an EGL traceback).
_OPEN_RENDERERS: weakref.WeakSet = weakref.WeakSet()
_EXIT_HOOK_REGISTERED = False


def _track_open_renderer(renderer: FirstPersonRenderer) -> None:
    """Remember ``renderer`` so it is closed at exit.

    The exit hook is registered after MuJoCo's first context, whose own exit hook
    (``eglTerminate``) must run after ours (``atexit`` runs hooks last-in first-out).
    """
    global _EXIT_HOOK_REGISTERED
    if not _EXIT_HOOK_REGISTERED:
        atexit.register(_close_open_renderers)
        _EXIT_HOOK_REGISTERED = True
    _OPEN_RENDERERS.add(renderer)


def _close_open_renderers() -> None:
    for renderer in list(_OPEN_RENDERERS):
        try:
            renderer.close()
        except Exception:  # best effort at exit
            logger.debug("could not close a renderer at exit", exc_info=True)


class RendererUnavailableError(RuntimeError):
    """Raised when no headless OpenGL back-end can be used."""


def _can_load(library: str) -> bool:
    path = ctypes.util.find_library(library)
    for candidate in (path, f"lib{library}.so", f"lib{library}.so.1", f"lib{library}.so.8"):
        if not candidate:
            continue
        try:
            ctypes.CDLL(candidate)
            return True
        except OSError:
            continue
    return False


def select_gl_backend() -> str:
    """Choose and export the MuJoCo GL back-end for this process.

    Runs at the first render (:func:`create_gl_context`), before ``mujoco`` creates
    a context; importing :mod:`envs` does not call it, so the process environment
    is left alone until something is drawn.

    Returns:
        the back-end name written to ``MUJOCO_GL`` (and ``PYOPENGL_PLATFORM``).

    Raises:
        RendererUnavailableError: if ``MUJOCO_GL`` names an unknown back-end, or
            neither EGL nor OSMesa can be loaded.
    """
    requested = os.environ.get("MUJOCO_GL")
    if requested:
        if requested not in SUPPORTED_GL_BACKENDS:
            raise RendererUnavailableError(
                f"MUJOCO_GL={requested!r} is not supported; allowed values are "
                f"{SUPPORTED_GL_BACKENDS}."
            )
        backend = requested
    elif _can_load("EGL"):
        backend = "egl"
    elif _can_load("OSMesa"):
        logger.warning("libEGL not found: falling back to MUJOCO_GL=osmesa (slower). %s", _INSTALL_HINT)
        backend = "osmesa"
    else:
        raise RendererUnavailableError(f"No headless OpenGL back-end found (EGL, OSMesa). {_INSTALL_HINT}")
    os.environ["MUJOCO_GL"] = backend
    if backend in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", backend)
    # llvmpipe is fastest single-threaded for small frames (notes/rendering-measurements.md).
    os.environ.setdefault("LP_NUM_THREADS", "0")
    return backend


def create_gl_context(width: int, height: int):
    """Create and make current a MuJoCo GL context of at least ``width`` x ``height`` pixels.

    Raises:
        RendererUnavailableError: with the back-end tried and the packages to install.
    """
    import importlib

    backend = select_gl_backend()
    try:
        # import the back-end module explicitly: ``mujoco.GLContext`` is bound when
        # ``mujoco`` is first imported, which may have happened before ``envs``.
        gl_module = importlib.import_module(f"mujoco.{backend}") if backend != "glfw" else importlib.import_module("mujoco.glfw")
        context = gl_module.GLContext(width, height)
        context.make_current()
    except Exception as err:  # re-raised with advice
        alternative = "osmesa" if backend == "egl" else "egl"
        raise RendererUnavailableError(
            f"Could not create a MuJoCo OpenGL context with MUJOCO_GL={backend!r} ({err}). "
            f"Try MUJOCO_GL={alternative}. {_INSTALL_HINT}"
        ) from err
    return context


@dataclass(frozen=True)
class FirstPersonView:
    """A compiled model and its eye height (metres), drawn as it is: for instance a dm_control
    physics' own model (:attr:`envs.dmc_physics.HousePhysics.first_person_view`).

    :class:`FirstPersonRenderer` draws a :class:`~envs.scenes.House` layout through its
    compiled model (:func:`envs.house_mesh.house_model`), or such a view.
    """

    model: object  # a mujoco.MjModel (mujoco is imported only once rendering starts)
    eye_height_m: float


@dataclass(frozen=True)
class RepeatView:
    """How a repeating robot's camera and light differ from the teacher's, for one episode
    (drawn by :mod:`envs.conditions`; ``None`` in place of a view is the teacher's own).

    Args:
        eye_offset_m: camera height above (or, negative, below) the house's eye height, metres.
        pitch_deg: camera pitch, degrees (positive: looking up).
        fovy_deg: vertical field of view, degrees.
        light_rgb: factors on the light's red, green and blue (ambient and diffuse).
        light_yaw_deg: the light's direction turned from the view direction, degrees (0: the
            teacher's headlight, which lights along the view).
        lamp_room: a room label where a lamp is the only light (``None``: no lamp).
        lamp_xyz: the lamp's position, metres.

    Examples:
        >>> RepeatView(pitch_deg=5.0).fovy_deg
        90.0
    """

    eye_offset_m: float = 0.0
    pitch_deg: float = 0.0
    fovy_deg: float = FIELD_OF_VIEW_DEG
    light_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    light_yaw_deg: float = 0.0
    lamp_room: str | None = None
    lamp_xyz: tuple[float, float, float] | None = None


#: Light left in a lamp-lit room besides the lamp (ambient, a fraction of the headlight's).
LAMP_ROOM_AMBIENT = 0.15
#: The lamp's diffuse colour and its attenuation (constant, linear, quadratic in metres).
LAMP_RGB = (1.0, 0.85, 0.6)
LAMP_ATTENUATION = (0.3, 0.0, 0.12)
#: Compiled models a renderer keeps GL resources for; the least recently drawn is freed
#: beyond this (a house's variants of :mod:`envs.conditions` come and go).
MAX_MODELS_PER_RENDERER = 24


def _model_of(scene: House | FirstPersonView):
    """The compiled model a scene is drawn from."""
    return scene.model if isinstance(scene, FirstPersonView) else house_model(scene)


class FirstPersonRenderer:
    """Renders RGB frames of MuJoCo models from a pose given in the xy plane.

    One renderer owns one GL context; it keeps a :class:`mujoco.MjrContext` per model
    (created on first use), so houses that differ are all drawn by the same context.
    Several renderers may live in one process (a collector's env beside an
    evaluation env): each makes its own context current before it draws, creates
    or frees GL resources.

    Args:
        width: frame width in pixels.
        height: frame height in pixels.

    Examples:
        >>> from envs.scenes import build_house
        >>> house = build_house(seed=0)
        >>> renderer = FirstPersonRenderer(64, 64)
        >>> frame = renderer.render(house, np.array([house.spawn_xy[0], house.spawn_xy[1], 0.0]))
        >>> frame.shape, frame.dtype
        ((64, 64, 3), dtype('uint8'))
    """

    def __init__(self, width: int, height: int) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"width and height must be positive pixel counts, got width={width}, height={height}.")
        self.width = int(width)
        self.height = int(height)
        self._gl = None
        # by id(model); each state holds its model, so an id is never reused while it is here
        self._per_model: OrderedDict[int, tuple] = OrderedDict()
        self._buffer = np.empty((self.height, self.width, 3), dtype=np.uint8)

    def _activate(self) -> None:
        """Make this renderer's GL context current on this thread (creating it on first use).

        Always re-bound (a few microseconds): another renderer may have made its own
        context current, and freeing any MuJoCo GL context (even by the garbage
        collector) calls ``eglReleaseThread``, which unbinds the current one.
        """
        if self._gl is None:
            self._gl = create_gl_context(self.width, self.height)
            _track_open_renderer(self)
        else:
            self._gl.make_current()

    def _model_state(self, house):
        import mujoco

        self._activate()
        key = id(_model_of(house))
        state = self._per_model.get(key)
        if state is None:
            model = _model_of(house)
            data = mujoco.MjData(model)
            mujoco.mj_forward(model, data)  # place every geom before the first scene update
            scene = mujoco.MjvScene(model, maxgeom=max(64, model.ngeom + 8))
            # an offscreen framebuffer of the frame's size (less to clear per frame); the
            # model may be shared with renderers of other sizes, so restore its setting
            visual = model.vis.global_
            saved = (visual.offwidth, visual.offheight)
            visual.offwidth, visual.offheight = self.width, self.height
            try:
                context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_50)
            finally:
                visual.offwidth, visual.offheight = saved
            _set_minification_filter(model, context)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, context)
            camera = mujoco.MjvCamera()
            camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
            camera.fixedcamid = 0
            option = mujoco.MjvOption()
            viewport = mujoco.MjrRect(0, 0, self.width, self.height)
            state = (model, data, scene, context, camera, option, viewport, house)
            self._per_model[key] = state
            while len(self._per_model) > MAX_MODELS_PER_RENDERER:
                _, evicted = self._per_model.popitem(last=False)
                evicted[3].free()
        else:
            self._per_model.move_to_end(key)
        return state

    def render(self, house, pose: np.ndarray, out: np.ndarray | None = None, view: RepeatView | None = None) -> np.ndarray:
        """Render the first-person view at ``pose`` = (x metres, y metres, heading radians),
        through ``view`` (``None``: the teacher's camera and light).

        Returns:
            an ``(height, width, 3)`` uint8 array (a new one unless ``out`` is given).
        """
        if out is None:
            out = np.empty_like(self._buffer)
        self.render_many([house], np.asarray(pose, dtype=np.float64)[None], out=out[None], views=[view])
        return out

    def render_many(
        self, houses, poses: np.ndarray, out: np.ndarray | None = None, views: Sequence[RepeatView | None] | None = None
    ) -> np.ndarray:
        """Render one frame per ``(house, pose)`` pair, binding the GL context once.

        Args:
            houses: a sequence of houses (repeats allowed).
            poses: ``(N, 3)`` poses, one per house.
            out: optional ``(N, height, width, 3)`` uint8 array (any strides, e.g. a
                CHW tensor's array transposed) that receives the frames.
            views: one :class:`RepeatView` (or ``None``: the teacher's) per frame; ``None``:
                every frame the teacher's.

        Returns:
            ``out``, or a new ``(N, height, width, 3)`` uint8 array.
        """
        import mujoco

        if out is None:
            out = np.empty((len(houses), self.height, self.width, 3), dtype=np.uint8)
        self._activate()
        offscreen = mujoco.mjtFramebuffer.mjFB_OFFSCREEN
        everything = mujoco.mjtCatBit.mjCAT_ALL
        current = None
        for row, house in enumerate(houses):
            key = id(_model_of(house))
            state = self._per_model.get(key)
            if state is None:
                state = self._model_state(house)
            else:
                self._per_model.move_to_end(key)
            model, data, scene, context, camera, option, viewport, _ = state
            if key != current:
                mujoco.mjr_setBuffer(offscreen, context)
                current = key
            pose = poses[row]
            view = None if views is None else views[row]
            if view is None:
                data.cam_xpos[0] = (pose[0], pose[1], house.eye_height_m)
                data.cam_xmat[0] = _camera_matrix(float(pose[2]))
                mujoco.mjv_updateScene(model, data, option, None, camera, everything, scene)
            else:
                _update_scene_through(view, house, pose, model, data, option, camera, scene)
            mujoco.mjr_render(viewport, scene, context)
            mujoco.mjr_readPixels(self._buffer, None, viewport, context)
            np.copyto(out[row], self._buffer[::-1])
        return out

    def models_held(self) -> int:
        """How many compiled models this renderer holds GL resources for (at most :data:`MAX_MODELS_PER_RENDERER`)."""
        return len(self._per_model)

    def release(self, house) -> None:
        """Free the GL resources held for ``house``'s model."""
        state = self._per_model.pop(id(_model_of(house)), None)
        if state is not None:
            self._activate()
            state[3].free()

    def close(self) -> None:
        """Free every model's GL resources and the context."""
        if self._gl is None:
            return
        self._activate()
        for state in self._per_model.values():
            state[3].free()
        self._per_model.clear()
        self._gl.free()
        self._gl = None
        _OPEN_RENDERERS.discard(self)


#: Minification filter set on 2-D textures (MuJoCo uploads them with trilinear
#: GL_LINEAR_MIPMAP_LINEAR): bilinear in the nearest mipmap level costs about 20%
#: less per frame on llvmpipe at 64 px and looks the same at these frame sizes.
TEXTURE_MIN_FILTER = "GL_LINEAR_MIPMAP_NEAREST"


def _set_minification_filter(model, context) -> None:
    """Set :data:`TEXTURE_MIN_FILTER` on the context's 2-D textures (skipped if PyOpenGL is missing)."""
    import mujoco

    try:
        from OpenGL import GL
    except ImportError:  # pragma: no cover - PyOpenGL comes with mujoco's egl/osmesa back-ends
        logger.debug("PyOpenGL not available: keeping MuJoCo's texture filtering.")
        return
    for index in range(model.ntex):
        if model.tex_type[index] == mujoco.mjtTexture.mjTEXTURE_2D:
            GL.glBindTexture(GL.GL_TEXTURE_2D, int(context.texture[index]))
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, getattr(GL, TEXTURE_MIN_FILTER))
    GL.glBindTexture(GL.GL_TEXTURE_2D, 0)


def _camera_matrix(heading_rad: float) -> np.ndarray:
    """Rotation (row-major 3x3, flattened) of a level camera looking along ``heading_rad``.

    MuJoCo cameras look along their local -z with +y up; the agent looks along
    (cos h, sin h, 0) with world +z up.
    """
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    # columns: camera x = right (s, -c, 0), camera y = up (0, 0, 1), camera z = backwards (-c, -s, 0)
    return np.array([s, 0.0, -c, -c, 0.0, -s, 0.0, 1.0, 0.0])


def _pitched_camera_matrix(heading_rad: float, pitch_rad: float) -> np.ndarray:
    """:func:`_camera_matrix` of a camera pitched by ``pitch_rad`` (positive: looking up)."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    # columns: right (s, -c, 0), up (-c sp, -s sp, cp), backwards (-c cp, -s cp, -sp)
    return np.array([s, -c * sp, -c * cp, -c, -s * sp, -s * cp, 0.0, cp, -sp])


@functools.lru_cache(maxsize=256)
def _light_factors(rgb: tuple[float, float, float]) -> np.ndarray:
    """A view's light factors as the scene's float32 (made once per view)."""
    factors = np.asarray(rgb, dtype=np.float32)
    factors.flags.writeable = False
    return factors


def _update_scene_through(view: RepeatView, house, pose: np.ndarray, model, data, option, camera, scene) -> None:
    """``mjv_updateScene`` for a camera and light changed by ``view``: the eye's height, pitch
    and field of view, then the headlight's colour and direction and a lamp, edited in the scene."""
    import mujoco

    heading = float(pose[2])
    data.cam_xpos[0] = (pose[0], pose[1], house.eye_height_m + view.eye_offset_m)
    data.cam_xmat[0] = _pitched_camera_matrix(heading, math.radians(view.pitch_deg))
    saved_fovy = float(model.cam_fovy[0])
    model.cam_fovy[0] = view.fovy_deg
    try:
        mujoco.mjv_updateScene(model, data, option, None, camera, mujoco.mjtCatBit.mjCAT_ALL, scene)
    finally:
        model.cam_fovy[0] = saved_fovy
    if scene.nlight == 0 or not scene.lights[0].headlight:
        return
    light, rgb = scene.lights[0], _light_factors(view.light_rgb)
    if view.lamp_room is not None and house.room_at(pose[:2]) == view.lamp_room:
        # the headlight becomes the lamp: a spot hanging from the ceiling, shining down on the
        # whole room (MuJoCo's classic renderer draws no point lights)
        light.type = mujoco.mjtLightType.mjLIGHT_SPOT
        light.headlight = 0
        light.pos[:] = view.lamp_xyz
        light.dir[:] = (0.0, 0.0, -1.0)
        light.ambient[:] = light.ambient * LAMP_ROOM_AMBIENT * rgb
        light.diffuse[:] = LAMP_RGB
        light.attenuation[:] = LAMP_ATTENUATION
        light.cutoff = 90.0
        light.exponent = 0.0
        return
    ambient, diffuse = light.ambient, light.diffuse  # views into the scene: scaled in place
    ambient *= rgb
    diffuse *= rgb
    if view.light_yaw_deg:
        turned = heading + math.radians(view.light_yaw_deg)
        light.headlight = 0
        light.type = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
        light.pos[:] = data.cam_xpos[0]
        light.dir[:] = (math.cos(turned), math.sin(turned), 0.0)


#: Colour of walls and of furniture on top-down maps (RGB in [0, 1]).
MAP_WALL_RGB = (0.15, 0.15, 0.18)
MAP_FURNITURE_RGB = (0.45, 0.35, 0.25)


def draw_top_down_map(house, paths=None, points=None, ax=None, title: str | None = None):
    """Draw a house from above (rooms tinted, walls, furniture) with paths and points on it.

    Args:
        house: a :class:`~envs.scenes.House`.
        paths: ``{label: (T, 2) or (T, 3) array}`` of positions (metres) drawn as lines.
        points: ``{label: (K, 2) array}`` drawn as markers (e.g. memory frame positions).
        ax: a matplotlib axis to draw on (a new figure otherwise).
        title: optional axis title.

    Returns:
        the matplotlib axis.

    Examples:
        >>> import matplotlib
        >>> matplotlib.use("Agg")
        >>> from envs.scenes import build_house
        >>> ax = draw_top_down_map(build_house(0), paths={"route": np.array([[1.5, 1.5], [3.5, 1.5]])})
        >>> tuple(float(v) for v in ax.get_xlim())
        (0.0, 15.0)
    """
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Rectangle

    if ax is None:
        _, ax = plt.subplots(figsize=(5, 5))
    labels = house.room_labels
    names = sorted({str(x) for x in np.unique(labels)})
    palette = plt.get_cmap("Pastel1")
    image = np.ones(labels.shape + (3,))
    for index, name in enumerate(names):
        image[labels == name] = palette(index % palette.N)[:3] if name != "." else (0.93, 0.93, 0.93)
    image[house.walls] = MAP_WALL_RGB
    width, depth = house.size_m
    ax.imshow(image, origin="lower", extent=(0, width, 0, depth), interpolation="nearest")
    for piece in house.furniture:
        if piece.kind == "box":
            hx, hy = piece.half_size_m
            ax.add_patch(Rectangle(piece.centre_xy - (hx, hy), 2 * hx, 2 * hy, color=MAP_FURNITURE_RGB))
        else:
            ax.add_patch(Circle(piece.centre_xy, piece.half_size_m[0], color=MAP_FURNITURE_RGB))
    for label, path in (paths or {}).items():
        path = np.asarray(path)
        ax.plot(path[:, 0], path[:, 1], "-", linewidth=2, label=label)
        ax.plot(path[0, 0], path[0, 1], "o", color="black", markersize=4)
    for label, xy in (points or {}).items():
        xy = np.asarray(xy)
        ax.plot(xy[:, 0], xy[:, 1], "*", markersize=9, label=label)
    if paths or points:
        ax.legend(loc="upper right", fontsize=7)
    ax.set_xlim(0, width)
    ax.set_ylim(0, depth)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title)
    return ax
