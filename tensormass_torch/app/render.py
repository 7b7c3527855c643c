"""Off-screen pictures of bodies: PNG stills and animated GIFs, drawn with pyvista (VTK).

pyvista is imported only when something is rendered, so the package imports without it
(``pip install pyvista``, or ``pip install -e .[render]``).

    from tensormass_torch.app.render import render_png, render_gif
    render_png("twist.png", [[(mesh, None), (mesh, x_hooke)], [(mesh, None), (mesh, x_corot)]],
               labels=["hooke", "corotational"])

A *panel* is one sub-view: a list of ``(mesh, positions)`` pairs drawn together (``positions``
``[V, 3]`` or ``[V, 2]``, a tensor or an array; ``None`` draws the rest shape). Panels are laid
side by side and share one camera, so their scales compare. Rigid tools are drawn translucent
in ``TOOL_COLOR`` (``tools=``; ``simulator_tools(sim)`` gives a simulator's, from
``app.shapes``).

Headless Linux (no X server, no xvfb): the pip ``vtk`` wheels (9.4 and later) choose their
OpenGL window at run time, trying X11, then EGL, then OSMesa. Without a ``DISPLAY`` this module
asks for EGL directly (``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``, unless you set that
variable yourself), which renders on a GPU's EGL driver or, with no GPU, on Mesa's software
rasteriser (Debian: ``libegl1 libegl-mesa0 libgl1-mesa-dri``). OSMesa is the other way
(``VTK_DEFAULT_OPENGL_WINDOW=vtkOSMesaRenderWindow``) and needs ``libOSMesa`` (``libosmesa6``).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np
import torch

from ..errors import SceneError
from ..mesh.topology import boundary_faces
from .shapes import TOOL_COLOR, tool_surface

#: Colours of the deformed entries of a panel, in order (rest shapes are drawn in REST_COLOR).
PALETTE = ("#4878cf", "#d65f5f", "#6acc65", "#b47cc7", "#c4ad66", "#77bedb")
REST_COLOR = "#b0b0b0"
REST_OPACITY = 0.35
TOOL_OPACITY = 0.6
CAMERAS = ("iso", "xy", "xz", "yz")
INSTALL_HINT = "pip install pyvista   (or: pip install -e '.[render]')"


def _pyvista():
    """Import pyvista for off-screen use; ImportError with an install hint when it is missing."""
    headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if headless and "VTK_DEFAULT_OPENGL_WINDOW" not in os.environ:
        # Skips VTK's X11 attempt (and its warning) on a machine with no X server.
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    try:
        import pyvista
    except ImportError as exc:
        raise ImportError(f"rendering needs pyvista, which is not installed ({exc}): {INSTALL_HINT}") from exc
    pyvista.OFF_SCREEN = True
    return pyvista


def _as_points(mesh, positions) -> np.ndarray:
    """Positions ``[V, 3]`` float64 numpy (2-D meshes and positions get z = 0)."""
    points = mesh.vertices if positions is None else positions
    if isinstance(points, torch.Tensor):
        points = points.detach().to("cpu", torch.float64).numpy()
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[0] != mesh.num_vertices or points.shape[1] not in (2, 3):
        raise SceneError(f"positions have shape {tuple(points.shape)}; expected [{mesh.num_vertices}, 3] "
                         f"or [{mesh.num_vertices}, 2] for this mesh")
    if not np.isfinite(points).all():
        raise SceneError("positions contain NaN or inf: nothing sensible to draw")
    if points.shape[1] == 2:
        points = np.concatenate([points, np.zeros((points.shape[0], 1))], axis=1)
    return points


def _surface(pv, mesh, positions):
    """A pyvista PolyData of the body's surface: boundary faces of tets, or the triangles themselves."""
    kind = getattr(mesh, "kind", None)
    if kind == "tet":
        triangles = boundary_faces(mesh.elements.cpu())
    elif kind == "tri":
        triangles = mesh.elements.long().cpu()
    else:
        raise SceneError(f"cannot draw a {type(mesh).__name__}: expected a TetMesh or a TriMesh")
    tri = triangles.numpy()
    faces = np.concatenate([np.full((tri.shape[0], 1), 3, dtype=np.int64), tri], axis=1).ravel()
    return pv.PolyData(_as_points(mesh, positions), faces)


def _tool_surfaces(pv, tools, num_panels: int, what: str = "tools"):
    """pyvista PolyData of ``tools`` (None, or one list per panel of ``(vertices [K, 3], triangles
    [F, 3])`` in world coordinates), one list per panel; SceneError naming a malformed one."""
    if tools is None:
        return [[] for _ in range(num_panels)]
    if not isinstance(tools, (list, tuple)) or len(tools) != num_panels:
        raise SceneError(f"{what} must be one list of (vertices, triangles) per panel ({num_panels}), got "
                         f"{type(tools).__name__}{'' if not isinstance(tools, (list, tuple)) else f' of {len(tools)}'}")
    drawn = []
    for i, panel in enumerate(tools):
        row = []
        for j, item in enumerate(panel):
            where = f"{what}[{i}][{j}]"
            if not (isinstance(item, (list, tuple)) and len(item) == 2):
                raise SceneError(f"{where} must be a (vertices [K, 3], triangles [F, 3]) pair")
            points = np.asarray(torch.as_tensor(item[0]).detach().cpu(), dtype=np.float64)
            faces = np.asarray(torch.as_tensor(item[1]).detach().cpu())
            if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
                raise SceneError(f"{where}: vertices must be [K, 3] and finite, got shape {points.shape}")
            if (faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0
                    or not np.issubdtype(faces.dtype, np.integer) or faces.min() < 0 or faces.max() >= len(points)):
                raise SceneError(f"{where}: triangles must be [F >= 1, 3] integer ids of its {len(points)} vertices")
            cells = np.concatenate([np.full((faces.shape[0], 1), 3, dtype=np.int64), faces.astype(np.int64)], axis=1)
            row.append(pv.PolyData(points, cells.ravel()))
        drawn.append(row)
    return drawn


def simulator_tools(simulator) -> list:
    """The tools of ``simulator`` where they are now, as :func:`render_png` takes them for one
    panel: ``[(vertices [K, 3], triangles [F, 3]), ...]`` (empty without tools)."""
    if simulator.tools is None:
        return []
    return [(vertices + np.asarray(simulator.tools.origin_at(k, simulator.time)), faces)
            for k, (vertices, faces) in enumerate(tool_surface(tool) for tool in simulator.tools.tools)]


def _check_panels(panels, what: str = "panels"):
    if not isinstance(panels, (list, tuple)) or not panels:
        raise SceneError(f"{what} must be a non-empty list of panels (each a list of (mesh, positions) pairs)")
    for i, panel in enumerate(panels):
        if not isinstance(panel, (list, tuple)) or not panel:
            raise SceneError(f"{what}[{i}] must be a non-empty list of (mesh, positions) pairs")
        for j, item in enumerate(panel):
            if not (isinstance(item, (list, tuple)) and len(item) == 2):
                raise SceneError(f"{what}[{i}][{j}] must be a (mesh, positions) pair")


def _colors_for(colors, panel_index: int, panel) -> list:
    """One colour per entry of a panel: ``colors`` is None, one list for every panel, or one list per panel."""
    chosen, deformed = [], 0
    custom = None
    if colors:
        # an RGB triple is one colour, any other list or tuple is the colours of one panel
        per_panel = isinstance(colors[0], (list, tuple)) and not all(isinstance(c, (int, float)) for c in colors[0])
        custom = colors[panel_index] if per_panel else colors
    for j, (_, positions) in enumerate(panel):
        if custom is not None and j < len(custom) and custom[j] is not None:
            chosen.append(custom[j])
        elif positions is None:
            chosen.append(REST_COLOR)
        else:
            chosen.append(PALETTE[deformed % len(PALETTE)])
            deformed += 1
    return chosen


def _bounds(surfaces) -> list:
    """Union of the surfaces' bounds ``[xmin, xmax, ymin, ymax, zmin, zmax]``."""
    lo = np.min([s.points.min(axis=0) for s in surfaces], axis=0)
    hi = np.max([s.points.max(axis=0) for s in surfaces], axis=0)
    return [lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]]


def _set_camera(plotter, camera, bounds, zoom):
    if isinstance(camera, str):
        if camera not in CAMERAS:
            raise SceneError(f"unknown camera {camera!r}; expected one of {', '.join(CAMERAS)} "
                             "or a pyvista camera position")
        getattr(plotter, "view_isometric" if camera == "iso" else f"view_{camera}")()
    else:
        plotter.camera_position = camera
    plotter.reset_camera(bounds=bounds)
    if zoom != 1.0:
        plotter.camera.zoom(zoom)


def _surfaces_of(pv, panels):
    return [[_surface(pv, mesh, positions) for mesh, positions in panel] for panel in panels]


def _draw(pv, panels, surfaces, bounds, *, window_size, labels, colors, camera, show_edges, zoom,
          tools=None) -> np.ndarray:
    """Render one picture (``tools``: the tools' PolyData per panel, or None); returns its pixels
    ``[H, W, 3]`` uint8."""
    plotter = pv.Plotter(off_screen=True, shape=(1, len(panels)), window_size=list(window_size),
                         border=False)
    try:
        plotter.set_background("white")
        for i, (panel, panel_surfaces) in enumerate(zip(panels, surfaces)):
            plotter.subplot(0, i)
            for (_, positions), surface, color in zip(panel, panel_surfaces, _colors_for(colors, i, panel)):
                rest = positions is None
                plotter.add_mesh(surface, color=color, show_edges=show_edges and not rest,
                                 edge_color="#303030", line_width=0.5,
                                 opacity=REST_OPACITY if rest else 1.0, smooth_shading=False)
            for shape in (tools[i] if tools is not None else ()):
                plotter.add_mesh(shape, color=TOOL_COLOR, opacity=TOOL_OPACITY, smooth_shading=True)
            if labels is not None and i < len(labels) and labels[i]:
                plotter.add_text(str(labels[i]), position="upper_edge", font_size=12, color="black")
        if len(panels) > 1:
            plotter.link_views()  # one camera: the panels compare at the same scale
        plotter.subplot(0, 0)
        _set_camera(plotter, camera, bounds, zoom)
        return np.asarray(plotter.screenshot(None, return_img=True))[..., :3].copy()
    finally:
        plotter.close()


def _check_window(window_size):
    if len(window_size) != 2 or any(int(w) < 16 for w in window_size):
        raise SceneError(f"window_size must be (width, height) of at least 16 pixels, got {window_size!r}")


def _check_zoom(zoom):
    if not (isinstance(zoom, (int, float)) and zoom > 0 and np.isfinite(zoom)):
        raise SceneError(f"zoom must be a positive number, got {zoom!r}")


def render_png(path, panels, *, window_size=(1200, 500), labels: Optional[Sequence[str]] = None,
               colors=None, camera="iso", show_edges: bool = True, zoom: float = 1.0, tools=None) -> Path:
    """Render ``panels`` side by side into the PNG file ``path``; returns its Path.

    Args:
        path: output file (its folder is created).
        panels: list of panels, each a list of ``(mesh, positions)`` pairs drawn together;
            ``mesh`` a TetMesh (its boundary surface is drawn) or TriMesh, ``positions``
            ``[V, 3]`` or ``[V, 2]`` (tensor or array) or None for the rest shape (drawn grey
            and translucent).
        window_size: ``(width, height)`` of the whole picture in pixels.
        labels: one title per panel (or None).
        colors: None (a palette), one colour per entry used in every panel, or one list per panel.
        camera: ``"iso"``, ``"xy"`` (looking down z), ``"xz"``, ``"yz"``, or a pyvista camera
            position ``[(position), (focal point), (view up)]``; zoomed to fit every panel.
        show_edges: draw element edges on deformed surfaces.
        zoom: magnification after the camera is fitted (> 1 fills more of each panel).
        tools: rigid tools to draw too (translucent, in ``TOOL_COLOR``): None, or one list per
            panel of ``(vertices [K, 3], triangles [F, 3])`` in world coordinates
            (:func:`simulator_tools` gives a simulator's, where they are now).

    Raises:
        ImportError: pyvista is not installed (the message says how to install it).
        SceneError: malformed panels or tools, positions of the wrong shape or non-finite, a bad
            camera.
    """
    _check_panels(panels)
    _check_window(window_size)
    _check_zoom(zoom)
    pv = _pyvista()
    surfaces = _surfaces_of(pv, panels)
    shapes = _tool_surfaces(pv, tools, len(panels))
    image = _draw(pv, panels, surfaces, _bounds([s for row in surfaces + shapes for s in row]),
                  window_size=window_size, labels=labels, colors=colors, camera=camera, show_edges=show_edges,
                  zoom=zoom, tools=shapes)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _image_module().fromarray(image).save(path, optimize=True)
    return path


def _image_module():
    try:
        from PIL import Image  # pillow is a dependency of pyvista
    except ImportError as exc:
        raise ImportError(f"writing images needs pillow ({exc}): pip install pillow") from exc
    return Image


def render_gif(path, frames, *, fps: float = 10.0, window_size=(1200, 500),
               labels: Optional[Sequence[str]] = None, colors=None, camera="iso",
               show_edges: bool = True, zoom: float = 1.0, tools=None) -> Path:
    """Render a sequence of ``frames`` (each a list of panels, as :func:`render_png` takes) into
    an animated GIF ``path`` that loops; returns its Path.

    The camera is fitted once to every frame's bounds, so the view holds still while the bodies
    move. Options as :func:`render_png`; ``fps`` frames per second (> 0); ``tools``: None, or
    one entry per frame, each as :func:`render_png`'s ``tools``.
    """
    if not isinstance(frames, (list, tuple)) or not frames:
        raise SceneError("frames must be a non-empty list, each frame a list of panels")
    if not (fps > 0):
        raise SceneError(f"fps must be > 0, got {fps!r}")
    for k, panels in enumerate(frames):
        _check_panels(panels, f"frames[{k}]")
    _check_window(window_size)
    _check_zoom(zoom)
    pv = _pyvista()
    Image = _image_module()
    if tools is not None and (not isinstance(tools, (list, tuple)) or len(tools) != len(frames)):
        raise SceneError(f"tools must be one entry per frame ({len(frames)}), got {type(tools).__name__}"
                         f"{'' if not isinstance(tools, (list, tuple)) else f' of {len(tools)}'}")
    all_surfaces = [_surfaces_of(pv, panels) for panels in frames]
    all_shapes = [_tool_surfaces(pv, None if tools is None else tools[k], len(panels), f"tools[{k}]")
                  for k, panels in enumerate(frames)]
    bounds = _bounds([s for surfaces, shapes in zip(all_surfaces, all_shapes) for row in surfaces + shapes
                      for s in row])
    images = [Image.fromarray(_draw(pv, panels, surfaces, bounds, window_size=window_size, labels=labels,
                                    colors=colors, camera=camera, show_edges=show_edges, zoom=zoom, tools=shapes))
              .convert("P", palette=Image.ADAPTIVE, colors=255)
              for panels, surfaces, shapes in zip(frames, all_surfaces, all_shapes)]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(round(1000.0 / fps)), loop=0,
                   optimize=True)
    return path


class FrameRenderer:
    """Off-screen pictures of the frames: ``<out>/<name>_<frame>.png`` and/or ``<out>/<name>.gif``.

    Every body of the simulator is drawn in one view, with its tools where they are
    (:func:`simulator_tools`). PNGs are written as frames arrive; the GIF is written by
    :meth:`close` from the positions kept for each frame (CPU copies ``[V_i, 3]``).
    pyvista is imported at construction, so a missing pyvista fails before any frame is
    simulated or written.
    """

    def __init__(self, out_dir, name: str, *, png: bool = True, gif: bool = False,
                 window_size=(800, 600), fps: float = 10.0):
        _pyvista()  # fail now (ImportError with an install hint), not after the run
        self.out_dir = Path(out_dir)
        self.name = name
        self.png, self.gif = png, gif
        self.window_size = tuple(window_size)
        self.fps = fps
        self.frame = 0
        self.frames: List[list] = []
        self.frame_tools: List[list] = []
        self.files: List[Path] = []

    def _panels(self, simulator) -> list:
        return [[(simulator.mesh(i), simulator.positions(i).detach().cpu())
                 for i in range(simulator.num_bodies)]]

    def write(self, simulator) -> None:
        """Draw the current state of every body of ``simulator``, and its tools where they are."""
        panels, tools = self._panels(simulator), [simulator_tools(simulator)]
        if self.png:
            file = self.out_dir / f"{self.name}_{self.frame:05d}.png"
            self.files.append(render_png(file, panels, window_size=self.window_size, tools=tools))
        if self.gif:
            self.frames.append(panels)
            self.frame_tools.append(tools)
        self.frame += 1

    def close(self) -> None:
        """Write the GIF of every frame drawn so far (if asked for)."""
        if self.gif and self.frames:
            file = self.out_dir / f"{self.name}.gif"
            self.files.append(render_gif(file, self.frames, fps=self.fps, window_size=self.window_size,
                                         tools=self.frame_tools))
            self.frames, self.frame_tools = [], []
