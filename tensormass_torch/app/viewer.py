"""A live simulation in the browser: ``tm.view(sim)`` and ``tensormass view SCENE``.

The page is viser's (a well-kept library made for this: a three.js client, a websocket server,
GUI widgets, transform gizmos and click rays, all driven from Python). The simulation steps in a
thread of its own, so the page stays responsive; every change a user asks for (play, a tool
moved, a cut, another dt or material) is queued and applied by that thread between steps, so
the simulator is only ever touched by one thread.

Frames: after each batch of steps the bodies' surfaces are sent (positions, and colours by
displacement, stress or none). The batch adapts to the frame rate: when the device is faster
than the display, several steps run per frame (and chain on a GPU), so the viewer costs the
simulation about one surface copy a frame.

Interaction:
  - tools: each of the scene's tools has a transform gizmo; dragging it holds the tool where it
    is put (``Simulator.move_tool``), and the panel shows the force the bodies put on it;
  - cutting: "Cut" then two clicks across a body: the blade is the surface the two click rays
    sweep (every face between them in depth is cut, ``Simulator.cut``);
  - grabbing: "Grab a node" then a click: the surface node nearest the click ray is held
    (``Simulator.hold_nodes``) and follows a gizmo until "Release";
  - controls: play / pause / step / reset, dt, the CG budget, the material model and Young's
    modulus (a new simulator at the initial state), the colouring.

The same actions are methods of :class:`Viewer` (what the tests and scripts drive).
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import io
import math
import queue
import socket
import threading
import time
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import SceneError, SolverError, TensorMassError
from ..mesh.cutting import Blade
from ..mesh.geometry import shape_vectors
from ..mesh.topology import boundary_faces
from .shapes import TOOL_RGB, tool_surface

INSTALL_HINT = "pip install viser   (or: pip install -e '.[viewer]')"
COLORINGS = ("displacement", "stress", "none")
BODY_COLOR = (72, 120, 207)
#: frames a second the adaptive batch of steps aims at
FRAME_RATE = 30.0
#: the most steps one frame takes (a chain on a GPU)
MAX_STEPS_PER_FRAME = 256


class ViewerError(TensorMassError):
    """The viewer could not start (a port in use, viser missing)."""


def _viser():
    try:
        import viser
    except ImportError as exc:
        raise ViewerError(f"the viewer needs viser, which is not installed ({exc}): {INSTALL_HINT}") from exc
    return viser


def _check_port(host: str, port: int) -> None:
    """One clear error where (host, port) cannot be bound (viser would quietly take the next port)."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ViewerError(f"port must be an integer in [0, 65535], got {port!r}")
    if port == 0:
        return
    probe = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    # as the server binds (asyncio sets it): a port whose last connections linger in TIME_WAIT is free
    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        probe.bind((host, port))
    except OSError as exc:
        raise ViewerError(f"cannot serve on {host}:{port} ({exc.strerror or exc}): the port is in use or the "
                          f"address is not this machine's; choose another with --port / port=") from None
    finally:
        probe.close()


def _colormap(values: np.ndarray) -> np.ndarray:
    """Values in [0, 1] ``[n]`` -> RGB ``[n, 3]`` uint8 (blue, through white, to red)."""
    t = np.clip(values, 0.0, 1.0)[:, None]
    blue, white, red = np.array([59, 76, 192.0]), np.array([221, 221, 221.0]), np.array([180, 4, 38.0])
    low = blue + (white - blue) * (t / 0.5)
    high = white + (red - white) * ((t - 0.5) / 0.5)
    return np.where(t < 0.5, low, high).astype(np.uint8)


def nodal_von_mises(x: torch.Tensor, elements: torch.Tensor, m: torch.Tensor, lam: torch.Tensor,
                    mu: torch.Tensor) -> torch.Tensor:
    """The von Mises norm of the St Venant-Kirchhoff stress S = lam tr(E) I + 2 mu E of each
    tetrahedron's Green strain E = (F^T F - I) / 2 (F = sum_a x_a m_a^T, shape vectors ``m [N, 4,
    3]``, ``lam``, ``mu [N]``) at positions ``x [V, 3]``, averaged on the nodes ``[V]`` (float64):
    a colour that shows where a body is loaded."""
    xd = x.double()
    eye = torch.eye(3, dtype=xd.dtype)
    grad = torch.einsum("nai,naj->nij", xd[elements], m)
    strain = 0.5 * (grad.transpose(1, 2) @ grad - eye)
    trace = strain.diagonal(dim1=1, dim2=2).sum(-1)
    stress = (lam * trace)[:, None, None] * eye + 2.0 * mu[:, None, None] * strain
    deviator = stress - (stress.diagonal(dim1=1, dim2=2).sum(-1) / 3.0)[:, None, None] * eye
    mises = torch.sqrt(1.5 * (deviator * deviator).sum((1, 2)))
    nodes = elements.reshape(-1)
    total = torch.zeros(x.shape[0], dtype=xd.dtype).index_add_(0, nodes, mises.repeat_interleave(elements.shape[1]))
    count = torch.zeros(x.shape[0], dtype=xd.dtype).index_add_(0, nodes, torch.ones(nodes.numel(), dtype=xd.dtype))
    return total / count.clamp(min=1.0)


@dataclasses.dataclass
class _Surface:
    """A body's surface as drawn: triangles ``[F, 3]`` in its node ids and what colours need."""

    faces: np.ndarray
    elements: torch.Tensor
    shape: Optional[tuple] = None  # (m [N, n, 3], lam [N], mu [N]) of tetrahedra, for stress


class Viewer:
    """A simulation served live to the browser (module docstring).

    Args:
        scene: a ``tm.Simulator`` or a scene (``tm.load_scene``, a built-in scene): what to run.
        host, port: where to serve (127.0.0.1: this machine only; port 0: any free one).
        coloring: ``"displacement"`` (default), ``"stress"`` (von Mises of the St Venant-Kirchhoff
            stress of the Green strain, averaged on the nodes) or ``"none"``.
        record: a folder to write the frames to (``.vtu`` + ``.pvd``, ``sim.output``), or None.
        gif: with ``record``, also an animated GIF of the frames (pyvista).
        playing: start stepping at once (else paused).
        steps: stop (pause) after this many steps (None: run until paused).
    """

    def __init__(self, scene, *, host: str = "127.0.0.1", port: int = 8080, coloring: str = "displacement",
                 record=None, gif: bool = False, playing: bool = True, steps: Optional[int] = None):
        from ..sim.simulator import Simulator

        sim = scene if isinstance(scene, Simulator) else getattr(scene, "simulator", None)
        if not isinstance(sim, Simulator):
            raise SceneError(f"view: expected a tm.Simulator or a scene, got {type(scene).__name__}")
        if coloring not in COLORINGS:
            raise SceneError(f"coloring must be one of {', '.join(map(repr, COLORINGS))}, got {coloring!r}")
        if gif and record is None:
            raise SceneError("gif=True needs record= (the folder the GIF goes to)")
        if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
            raise SceneError(f"steps must be a positive integer or None, got {steps!r}")
        viser = _viser()
        _check_port(host, port)
        self.name = getattr(scene, "name", "simulation")
        self.sim = sim
        self._initial_options = sim.options
        self.coloring = coloring
        self.playing = bool(playing)
        self.max_steps = steps
        self.steps_per_frame = 1
        self.frames = 0
        self.steps_per_second = 0.0
        self.error: Optional[str] = None
        self._commands: "queue.SimpleQueue" = queue.SimpleQueue()
        self._stop = threading.Event()
        self._idle = threading.Event()
        self._lock = threading.Lock()
        self._surfaces = {}
        self._meshes = {}  # body -> (its _Surface, "plain" | "colored", the scene node drawn)
        self._frames: "queue.Queue" = queue.Queue(maxsize=1)
        self._drawing = threading.Event()  # a frame is waiting or being drawn
        self._status = None
        self._cut_rays = None  # the first click of a cut, waiting for the second
        self._grabbing = False  # the next click grabs a node
        self._grabbed = None  # (body, node) held by the drag gizmo
        self._drag_gizmo = None
        self._writer = self._renderer = None
        if record is not None:
            from ..sim.output import FrameWriter

            self._writer = FrameWriter(record, self.name)
            if gif:
                from .render import FrameRenderer

                self._renderer = FrameRenderer(record, self.name, png=False, gif=True)
        with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner (the URL is the caller's to say)
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        if port and self.server.get_port() != port:  # (taken between the probe and viser's bind)
            self.server.stop()
            raise ViewerError(f"cannot serve on {host}:{port}: the port is in use; choose another with --port / port=")
        self.host, self.port = host, self.server.get_port()
        try:
            self._build_scene()
            self._build_gui()
            self._publish()
        except BaseException:
            self.server.stop()  # nothing left serving
            raise
        self._thread = threading.Thread(target=self._loop, name="tensormass-viewer", daemon=True)
        self._frame_thread = threading.Thread(target=self._frame_loop, name="tensormass-viewer-frames", daemon=True)
        self._thread.start()
        self._frame_thread.start()

    # ------------------------------------------------------------------ public actions (thread-safe)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def run(self, fn: Callable[[], object], wait: bool = True):
        """Run ``fn()`` on the simulation thread between steps; with ``wait``, its result (or its
        exception). What every action below goes through."""
        if self._stop.is_set():
            raise ViewerError("the viewer is closed")
        future: concurrent.futures.Future = concurrent.futures.Future()
        self._commands.put((fn, future))
        return future.result(timeout=600) if wait else future

    def play(self):
        self.run(lambda: self._set_playing(True))

    def pause(self):
        self.run(lambda: self._set_playing(False))

    def _set_playing(self, playing: bool):
        self.playing = playing
        self._play_button.label = "Pause" if playing else "Play"

    def step(self, n: int = 1):
        """``n`` steps now (paused or not), then a frame."""
        def work():
            self._advance(int(n))
            self._publish()
        self.run(work)

    def reset(self, **changes):
        """A new simulator at the initial state (``Simulator.rebuilt``; ``changes``: its settings),
        the tools back on their paths."""
        self.run(lambda: self._replace(self.sim.rebuilt(**changes)))

    def set_options(self, **changes):
        """Change step options (``dt``, ``cg_max_iter``, ``cg_tol``, ``require_convergence``...)
        from the next step on."""
        def work():
            options = dataclasses.replace(self.sim.options, **changes)
            self.sim.options = options
        self.run(work)

    def set_material(self, model: Optional[str] = None, young: Optional[float] = None):
        """Every body with another material model and/or Young's modulus: a new simulator of
        these bodies at the initial state."""
        from ..sim.simulator import Body

        def work():
            bodies = []
            for b in self.sim.initial_bodies:
                material = dataclasses.replace(b.material, **{k: v for k, v in (("model", model), ("young", young))
                                                              if v is not None})
                bodies.append(Body(b.mesh, material, fixed=b.fixed, prescribed=b.prescribed, motion=b.motion,
                                   velocity=b.velocity, name=b.name))
            self._replace(self.sim.rebuilt(bodies))
        self.run(work)

    def move_tool(self, tool, position):
        """Hold a tool at ``position`` (``Simulator.move_tool``) from the next step on."""
        self.run(lambda: self.sim.move_tool(tool, position))
        self._tool_moved(tool, position)

    def cut(self, first_ray, second_ray, body=None) -> int:
        """Cut along the surface two rays ``(origin, direction)`` sweep (two clicks across a body),
        from near their origins to beyond the scene; ``body``: a body (default: every 3-D body the
        blade crosses). Returns the nodes the cut added."""
        blade = self._blade(first_ray, second_ray)

        def work():
            sim = self.sim
            targets = [body] if body is not None else [i for i in range(sim.num_bodies)
                                                       if sim.bodies[i].mesh.kind == "tet"]
            added = sum(sim.cut(i, blade, missing_ok=True) for i in targets)
            self._surfaces.clear()
            self._meshes.clear()
            self._publish()
            return added
        return self.run(work)

    def grab(self, ray):
        """Pick the surface node nearest to a ray ``(origin, direction)`` (a click) and hold it
        where it is (``Simulator.hold_nodes``); a gizmo then drags it (:meth:`drag`). Returns
        (body, node id in its mesh)."""
        origin, direction = (np.asarray(v, dtype=np.float64) for v in ray)
        if origin.shape != (3,) or direction.shape != (3,) or not np.isfinite(np.r_[origin, direction]).all():
            raise SceneError(f"a grab's ray must be an origin and a direction of 3 finite numbers, got {ray!r}")
        direction = direction / max(float(np.linalg.norm(direction)), 1e-300)

        def work():
            best = None
            for i in range(self.sim.num_bodies):
                nodes = np.unique(self._surface(i).faces)
                x = self.sim.positions(i).detach().cpu().double().numpy()[nodes]
                along = (x - origin) @ direction
                distance = np.linalg.norm(x - origin - along[:, None] * direction, axis=1)
                distance[along < 0] = np.inf  # behind the camera
                k = int(np.argmin(distance))
                if best is None or distance[k] < best[0]:
                    best = (distance[k], i, int(nodes[k]), x[k])
            _, body, node, where = best
            self.sim.hold_nodes(body, [node], where[None])
            self._grabbed = (body, node)
            return body, node, where

        body, node, where = self.run(work)
        with self._lock:
            self._drag_gizmo = self.server.scene.add_transform_controls(
                "/grabbed", scale=0.15 * self._scene_size, disable_rotations=True, position=tuple(where))

            @self._drag_gizmo.on_update
            def _(event):
                self.drag(tuple(float(v) for v in self._drag_gizmo.position), wait=False)
        return body, node

    def drag(self, position, wait: bool = True):
        """Hold the grabbed node at ``position`` from the next step on."""
        def work():
            if self._grabbed is None:
                raise SceneError("drag: no node is grabbed (grab one first)")
            body, node = self._grabbed
            self.sim.hold_nodes(body, [node], [list(position)])
        return self.run(work, wait=wait)

    def release(self):
        """Let the grabbed node go."""
        def work():
            self.sim.release_nodes()
            self._grabbed = None
        self.run(work)
        with self._lock:
            if self._drag_gizmo is not None:
                self._drag_gizmo.remove()
                self._drag_gizmo = None

    def set_coloring(self, coloring: str):
        if coloring not in COLORINGS:
            raise SceneError(f"coloring must be one of {', '.join(map(repr, COLORINGS))}, got {coloring!r}")

        def work():
            self.coloring = coloring
            if self._coloring_menu.value != coloring:
                self._coloring_menu.value = coloring
            self._publish()
        self.run(work)

    def wait_steps(self, count: int, timeout: float = 120.0) -> None:
        """Block until the simulator has taken at least ``count`` steps (raises on a timeout or a
        stopped viewer)."""
        deadline = time.monotonic() + timeout
        while self.sim.steps_done < count:
            if self._stop.is_set() or time.monotonic() > deadline:
                raise TimeoutError(f"the viewer took {self.sim.steps_done} of {count} steps")
            time.sleep(0.01)

    def wait_closed(self) -> None:
        """Block until the viewer stops (:meth:`close`, Ctrl-C, or the last page closed with
        ``exit_on_close``)."""
        try:
            while not self._stop.wait(0.2):
                pass
        except KeyboardInterrupt:
            pass
        self.close()

    def exit_on_close(self) -> None:
        """Stop the viewer once a page has connected and every page has closed."""
        # viser counts a page as a client only once its first camera message has come, and runs
        # no client callback for a page that closes before that (a page closed at once, a loaded
        # machine): so the pages are counted by their connections, whose opening and closing
        # viser's connection server reports in order, one connection at a time
        connections = getattr(self.server, "_websock_server", None)
        if callable(getattr(connections, "on_client_connect", None)) \
                and callable(getattr(connections, "on_client_disconnect", None)):
            live, lock = set(), threading.Lock()

            def opened(connection):
                with lock:
                    live.add(connection.client_id)

            def closed(connection):
                with lock:
                    live.discard(connection.client_id)
                    if not live:
                        self._stop.set()

            connections.on_client_connect(opened)
            connections.on_client_disconnect(closed)
            return

        @self.server.on_client_disconnect  # (a viser without that server: its clients, as above)
        def _(client):
            if not any(c.client_id != client.client_id for c in self.server.get_clients().values()):
                self._stop.set()

    def close(self) -> None:
        """Stop stepping and serving; what was recorded is flushed. Idempotent."""
        self._stop.set()
        for thread in (self._thread, self._frame_thread):
            if thread.is_alive() and threading.current_thread() is not thread:
                thread.join(timeout=30)
        with self._lock:
            if self._renderer is not None:
                self._renderer.close()
                self._renderer = None
            if self.server is not None:
                with contextlib.redirect_stdout(io.StringIO()):  # (its "Server stopped")
                    self.server.stop()
                self.server = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ the simulation thread

    def _loop(self):
        while not self._stop.is_set():
            self._run_commands()
            if not self.playing:
                self._idle.set()
                self._stop.wait(0.02)
                continue
            self._idle.clear()
            start = time.perf_counter()
            count = self.steps_per_frame
            if self.max_steps is not None:
                count = min(count, self.max_steps - self.sim.steps_done)
                if count <= 0:
                    self._set_playing(False)
                    continue
            if not self._advance(count):
                continue
            elapsed = time.perf_counter() - start
            # several steps a frame where the device is faster than the display
            target = count * (1.0 / FRAME_RATE) / max(elapsed, 1e-6)
            self.steps_per_frame = int(max(1, min(MAX_STEPS_PER_FRAME, round(0.5 * (count + target)))))
            self.steps_per_second = count / max(elapsed, 1e-9)
            self._publish(now=False)

    def _run_commands(self):
        while True:
            try:
                fn, future = self._commands.get_nowait()
            except queue.Empty:
                return
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(fn())
                except BaseException as exc:  # noqa: BLE001 (handed to the caller)
                    future.set_exception(exc)

    def _advance(self, count: int) -> bool:
        """``count`` steps; a failed step pauses with its message on the page."""
        try:
            self.sim.step(count)
            if self.sim.device.type == "cuda":
                torch.cuda.synchronize(self.sim.device)
        except (SolverError, SceneError) as exc:
            self._set_playing(False)
            self.error = str(exc)
            self._show_status()
            return False
        self.error = None
        return True

    def _replace(self, sim):
        self.sim = sim
        self._grabbed = None
        if self._drag_gizmo is not None:
            self._drag_gizmo.remove()
            self._drag_gizmo = None
        self._surfaces.clear()
        self._meshes.clear()
        self.error = None
        self._reset_tools()
        self._publish()

    # ------------------------------------------------------------------ drawing

    def _surface(self, i: int) -> _Surface:
        surface = self._surfaces.get(i)
        if surface is None:
            mesh = self.sim.mesh(i)
            elements = mesh.elements.long().cpu()
            faces = boundary_faces(elements) if mesh.kind == "tet" else elements
            shape = None
            if mesh.kind == "tet":
                from ..ops.reference.stress_form import lame

                rest = self.sim.model.rest[self.sim.ptr[i]:self.sim.ptr[i] + mesh.num_vertices].cpu().double()
                m, _ = shape_vectors(rest[elements])
                material = self.sim.bodies[i].material
                young = material.per_element("young", elements.shape[0], m).double()
                poisson = material.per_element("poisson", elements.shape[0], m).double()
                shape = (m, *lame(young, poisson))
            surface = self._surfaces[i] = _Surface(faces.numpy().astype(np.uint32), elements, shape)
        return surface

    def _colors(self, surface: _Surface, x: torch.Tensor, rest: torch.Tensor, coloring: str) -> Optional[np.ndarray]:
        """Per-node colours ``[V_i, 3]`` uint8 of a body at ``x`` (``rest``: its rest positions),
        or None (one colour)."""
        if coloring == "none":
            return None
        if coloring == "stress" and surface.shape is not None:
            value = nodal_von_mises(x, surface.elements, *surface.shape).numpy()
        else:
            value = torch.linalg.vector_norm(x - rest, dim=1).double().numpy()
        top = float(value.max()) if value.size else 0.0
        return _colormap(value / top if top > 0 else value)

    def _publish(self, now: bool = True):
        """A frame of the bodies as they are now: their positions copied to the host here (the
        simulation thread), recorded, and drawn: at once (``now``), or by the frame thread while
        the simulation goes on (skipped if it is still drawing the last one)."""
        if not now and self._drawing.is_set():
            return
        sim = self.sim
        bodies = []
        for i in range(sim.num_bodies):
            surface = self._surface(i)
            x = sim.positions(i).detach().cpu()
            bodies.append((i, surface, x, sim.model.rest[sim.ptr[i]:sim.ptr[i] + x.shape[0]].cpu()))
        frame = (bodies, self.coloring, self._status_lines())
        if self._writer is not None:
            self._writer.write(sim)
        if self._renderer is not None:
            self._renderer.write(sim)
        if now:
            self._draw(frame)
        else:
            self._drawing.set()
            self._frames.put(frame)

    def _frame_loop(self):
        while not self._stop.is_set():
            try:
                frame = self._frames.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                self._draw(frame)
            finally:
                self._drawing.clear()

    def _draw(self, frame):
        """Send a frame's surfaces (and the panel's text) to the pages."""
        import trimesh

        bodies, coloring, lines = frame
        with self._lock:
            if self.server is None:
                return
            for i, surface, x, rest in bodies:
                points = x.double().numpy()
                colors = self._colors(surface, x, rest, coloring)
                handle = self._meshes.get(i)
                if colors is None:
                    if handle is not None and handle[0] is surface and handle[1] == "plain":
                        handle[2].vertices = points  # the same triangles: the positions alone
                        continue
                    node = self.server.scene.add_mesh_simple(f"/bodies/{i}", points, surface.faces, color=BODY_COLOR,
                                                             side="double")
                    self._meshes[i] = (surface, "plain", node)
                else:
                    mesh = trimesh.Trimesh(points, surface.faces, vertex_colors=colors, process=False)
                    self._meshes[i] = (surface, "colored", self.server.scene.add_mesh_trimesh(f"/bodies/{i}", mesh))
            self.frames += 1
            if self._status is not None:
                self._status.content = "\n".join(lines)

    def _status_lines(self) -> list:
        """The panel's text: time, steps, rate, each body's CG iterations and residual, the
        force on each tool, the last error."""
        sim = self.sim
        report = sim.last_report
        rate = (f", {self.steps_per_second:,.0f} steps/s ({self.steps_per_frame} a frame)" if self.playing
                else ", paused")
        lines = [f"**t = {sim.time:.3f} s**, {sim.steps_done} steps{rate}"]
        if report is not None and report.cg:
            iterations = report.cg_iterations.tolist()
            residual = report.cg[-1].relative_residual.tolist()
            for i in range(sim.num_bodies):
                name = sim.bodies[i].name or f"body {i}"
                lines.append(f"- {name}: CG {int(iterations[i])} it, residual {residual[i]:.1e}")
        if report is not None and report.contact is not None and len(report.contact.tool_force):
            for k, force in enumerate(report.contact.tool_force.tolist()):
                lines.append(f"- tool {k}: force ({force[0]:.3g}, {force[1]:.3g}, {force[2]:.3g}) N")
        if self.error:
            lines.append(f"\n**paused: {self.error}**")
        return lines

    def _show_status(self):
        with self._lock:
            if self._status is not None and self.server is not None:
                self._status.content = "\n".join(self._status_lines())

    def _build_scene(self):
        server, sim = self.server, self.sim
        x = sim.x.detach().cpu().double()
        low, high = x.min(0).values.numpy(), x.max(0).values.numpy()
        center, size = (low + high) / 2, float(np.linalg.norm(high - low)) or 1.0
        up = -sim.gravity.detach().cpu().double().numpy()
        up = up / np.linalg.norm(up) if np.linalg.norm(up) > 0 else np.array([0.0, 0.0, 1.0])
        server.scene.set_up_direction(tuple(up))
        side = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
        side = side / np.linalg.norm(side)
        server.initial_camera.position = tuple(center + size * (1.2 * side + 0.7 * up + 0.8 * np.cross(up, side)))
        server.initial_camera.look_at = tuple(center)
        self._scene_size = size
        if sim.planes is not None:
            for k, (normal, offset) in enumerate(zip(sim.planes.normals.cpu().double().numpy(),
                                                     sim.planes.offsets.cpu().double().numpy())):
                a = np.cross(normal, [1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.cross(normal, [0.0, 1.0, 0.0])
                a, b = a / np.linalg.norm(a), np.cross(normal, a / np.linalg.norm(a))
                origin = center - np.dot(center, normal) * normal + offset * normal
                corners = np.array([origin + size * (u * a + v * b) for u, v in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
                server.scene.add_mesh_simple(f"/planes/{k}", corners, np.array([[0, 1, 2], [0, 2, 3]]),
                                             color=(200, 200, 200), opacity=0.5, side="double")
        self._tool_handles = []
        self._reset_tools()
        server.scene.on_click()(self._on_click)

    def _reset_tools(self):
        server, sim = self.server, self.sim
        for handle in getattr(self, "_tool_handles", []):
            handle.remove()
        self._tool_handles = []
        if sim.tools is None:
            return
        for k, tool in enumerate(sim.tools.tools):
            origin = np.array(sim.tools.origin_at(k, sim.time))
            gizmo = server.scene.add_transform_controls(f"/tools/{k}", scale=0.3 * self._scene_size,
                                                        disable_rotations=True, position=tuple(origin))
            vertices, faces = tool_surface(tool)  # the pictures' shapes (app.shapes), about the gizmo
            server.scene.add_mesh_simple(f"/tools/{k}/shape", vertices, faces, color=TOOL_RGB, opacity=0.6)

            @gizmo.on_update
            def _(event, k=k, gizmo=gizmo):
                self.run(lambda: self.sim.move_tool(k, tuple(float(v) for v in gizmo.position)), wait=False)

            self._tool_handles.append(gizmo)

    def _tool_moved(self, tool, position):
        """The tool's gizmo (and shape) where the tool was put."""
        if isinstance(tool, str):
            names = [t.name for t in self.sim.tools.tools]
            tool = names.index(tool)
        self._tool_handles[tool].position = tuple(float(v) for v in position)

    def _blade(self, first_ray, second_ray) -> Blade:
        (o1, d1), (o2, d2) = ((np.asarray(o, dtype=np.float64), np.asarray(d, dtype=np.float64))
                              for o, d in (first_ray, second_ray))
        for name, v in (("origin", o1), ("direction", d1), ("origin", o2), ("direction", d2)):
            if v.shape != (3,) or not np.isfinite(v).all():
                raise SceneError(f"a cut's ray {name} must be 3 finite numbers, got {v.tolist()}")
        d1, d2 = d1 / max(np.linalg.norm(d1), 1e-300), d2 / max(np.linalg.norm(d2), 1e-300)
        far = 10.0 * self._scene_size + float(np.linalg.norm(o1) + np.linalg.norm(o2))
        return Blade.swept(o1, o1 + far * d1, o2, o2 + far * d2)

    def _on_click(self, event):
        if self._grabbing:
            self._grabbing = False
            self._grab_button.label = "Grab a node"
            try:
                self.grab((event.ray_origin, event.ray_direction))
            except TensorMassError as exc:
                self.error = str(exc)
                self._show_status()
            return
        if self._cut_rays is None:
            return
        if not self._cut_rays:
            self._cut_rays = [(event.ray_origin, event.ray_direction)]
            self._cut_button.label = "Cut: click the line's end"
            return
        first = self._cut_rays[0]
        self._cut_rays = None
        self._cut_button.label = "Cut"
        try:
            self.cut(first, (event.ray_origin, event.ray_direction))
        except TensorMassError as exc:
            self.error = str(exc)
            self._show_status()

    def _build_gui(self):
        gui = self.server.gui
        gui.add_markdown(f"**{self.name}**")
        play = self._play_button = gui.add_button("Pause" if self.playing else "Play")
        step = gui.add_button("Step")
        reset = gui.add_button("Reset")
        self._cut_button = gui.add_button("Cut")
        self._grab_button = gui.add_button("Grab a node")
        release = gui.add_button("Release")
        sim = self.sim
        dt = gui.add_number("dt (s)", sim.options.dt, min=1e-6, step=sim.options.dt / 10)
        budget = gui.add_number("CG budget (0: converge)", 0 if sim.options.require_convergence
                                else sim.options.cg_max_iter, min=0, step=1)
        model = gui.add_dropdown("Model", ("hooke", "stvk", "corotational"),
                                 initial_value=sim.bodies[0].material.model)
        young = gui.add_number("Young's modulus (Pa)", float(torch.as_tensor(sim.bodies[0].material.young).mean()),
                               min=1e-3)
        coloring = self._coloring_menu = gui.add_dropdown("Colour", COLORINGS, initial_value=self.coloring)
        self._status = gui.add_markdown("")

        @play.on_click
        def _(event):
            self.run(lambda: self._set_playing(not self.playing), wait=False)

        @step.on_click
        def _(event):
            self.step(1)

        @reset.on_click
        def _(event):
            self.reset()

        @self._cut_button.on_click
        def _(event):
            self._cut_rays = []
            self._cut_button.label = "Cut: click the line's start"

        @self._grab_button.on_click
        def _(event):
            if self._grabbed is not None:
                self.release()
            self._grabbing = True
            self._grab_button.label = "Grab: click a node"

        @release.on_click
        def _(event):
            self.release()

        @dt.on_update
        def _(event):
            if dt.value > 0:
                self.set_options(dt=float(dt.value))

        @budget.on_update
        def _(event):
            n = int(budget.value)
            if n > 0:
                self.set_options(cg_max_iter=n, require_convergence=False, cg_tol=0.0)
            else:  # the scene's own solver settings
                first = self._initial_options
                self.set_options(cg_max_iter=first.cg_max_iter, require_convergence=first.require_convergence,
                                 cg_tol=first.cg_tol)

        @model.on_update
        def _(event):
            self.set_material(model=model.value)

        @young.on_update
        def _(event):
            if young.value > 0 and math.isfinite(young.value):
                self.set_material(young=float(young.value))

        @coloring.on_update
        def _(event):
            if coloring.value != self.coloring:
                self.set_coloring(coloring.value)


def view(scene, *, host: str = "127.0.0.1", port: int = 8080, block: bool = True, exit_on_close: bool = False,
         **options) -> Viewer:
    """Serve a simulator or scene live in the browser (:class:`Viewer`; ``options``: its
    arguments) at http://host:port. ``block``: wait until it stops (Ctrl-C; with
    ``exit_on_close``, when the last page closes), then close it; else return it running."""
    viewer = Viewer(scene, host=host, port=port, **options)
    if exit_on_close:
        viewer.exit_on_close()
    if block:
        print(f"tensormass: viewing {viewer.name} at {viewer.url} (Ctrl-C to stop)", flush=True)
        viewer.wait_closed()
    return viewer


__all__ = ["Viewer", "ViewerError", "view", "COLORINGS"]
