"""The live viewer (app/viewer.py, ``tensormass view``): a real headless Chromium (the system's,
software WebGL) loads the page, the body shows in its pixels, a click on the page's Step button
and a tool moved through the viewer's API change the simulation; the actions (cut, reset,
materials, options, colours, recording); closing the page stops ``tensormass view
--exit-on-close``, also a page that closes before viser counts it as a client; a port in use
and an unknown scene give one clear error.

The browser tests skip, saying why, where no Chromium is installed (CI installs Debian's
chromium-headless-shell). ``TENSORMASS_SCREENSHOTS=DIR`` keeps the screenshot (the README's).
"""
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import tensormass_torch as tm

viser = pytest.importorskip("viser")
from tensormass_torch.app.viewer import Viewer, ViewerError, nodal_von_mises  # noqa: E402

SCENES = Path(__file__).resolve().parents[2] / "scenes"
BROWSERS = ("chromium-headless-shell", "chromium", "chromium-browser", "google-chrome")


def chromium():
    found = os.environ.get("TENSORMASS_CHROMIUM") or next(filter(None, map(shutil.which, BROWSERS)), None)
    if found is None:
        pytest.skip("no Chromium to drive (apt-get install chromium-headless-shell, or TENSORMASS_CHROMIUM=path)")
    pytest.importorskip("playwright")
    return found


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def open_page(playwright, url: str, size=(960, 600)):
    browser = playwright.chromium.launch(executable_path=chromium(), args=[
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"])
    page = browser.new_page(viewport={"width": size[0], "height": size[1]})
    page.goto(url)
    page.get_by_text("Connected").wait_for(timeout=60_000)
    return browser, page


def body_pixels(path) -> float:
    """The share of the picture's pixels in the viewer's body colour (blue over grey and white)."""
    from PIL import Image

    rgb = np.asarray(Image.open(path).convert("RGB")).astype(np.int32)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return float(((b > r + 50) & (b > g + 25)).mean())


def press_scene():
    return tm.load_scene(SCENES / "press.toml")


def test_the_page_shows_the_body_and_drives_the_simulation(tmp_path):
    """Chromium loads the page, the block is drawn (its colour covers part of the screenshot),
    the page's Step button steps the simulation, and a tool held lower by the viewer's API
    presses the block (force on the tool, nodes pushed down)."""
    from playwright.sync_api import sync_playwright

    chromium()
    viewer = Viewer(press_scene(), port=free_port(), playing=False, coloring="none")
    try:
        with sync_playwright() as playwright:
            browser, page = open_page(playwright, viewer.url)
            try:
                page.get_by_role("button", name="Step", exact=True).click()
                deadline = time.monotonic() + 60
                while viewer.sim.steps_done < 1 and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert viewer.sim.steps_done == 1  # the page's button stepped the simulation
                x = viewer.sim.positions(0)
                centre = int(torch.argmin(x[:, 0] ** 2 + x[:, 1] ** 2 + (x[:, 2] - x[:, 2].max()) ** 2))
                top = float(x[centre, 2])  # the top face's centre, under the sphere
                viewer.step(3)
                assert float(viewer.sim.last_report.contact.tool_force.norm()) == 0  # the sphere is above
                viewer.move_tool("probe", (0.0, 0.0, 0.22))
                viewer.step(15)
                assert float(viewer.sim.last_report.contact.tool_force[0, 2]) > 10.0
                assert float(viewer.sim.positions(0)[centre, 2]) < top - 0.005  # pressed down
                page.wait_for_timeout(3000)  # the frames reach the page
                for close in page.locator(".mantine-Notification-closeButton").all():  # "software WebGL"
                    close.click()
                page.wait_for_timeout(500)
                shot = tmp_path / "viewer.png"
                page.screenshot(path=str(shot))
            finally:
                browser.close()
        share = body_pixels(shot)
        assert share > 0.02, f"the body covers {share:.1%} of the screenshot"
        keep = os.environ.get("TENSORMASS_SCREENSHOTS")
        if keep:
            Path(keep).mkdir(parents=True, exist_ok=True)
            shutil.copy(shot, Path(keep) / "viewer.png")
    finally:
        viewer.close()


def test_closing_the_page_stops_the_command(tmp_path):
    """``tensormass view --exit-on-close``: serving until the page closes, then it exits (status
    0) and the port is free again."""
    from playwright.sync_api import sync_playwright

    chromium()
    port = free_port()
    process = subprocess.Popen([sys.executable, "-m", "tensormass_torch", "view", str(SCENES / "press.toml"),
                                "--port", str(port), "--exit-on-close", "--paused"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            with socket.socket() as probe:
                if probe.connect_ex(("127.0.0.1", port)) == 0:
                    break
            assert process.poll() is None, process.communicate()[1]
            time.sleep(0.2)
        with sync_playwright() as playwright:
            browser, page = open_page(playwright, f"http://127.0.0.1:{port}")
            page.close()
            browser.close()
        assert process.wait(timeout=60) == 0
        with socket.socket() as probe:
            assert probe.connect_ex(("127.0.0.1", port)) != 0  # nothing serves there any more
        Viewer(press_scene(), port=port, playing=False).close()  # and a viewer may take the port again
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_a_page_that_closes_before_its_first_camera_message_stops_the_viewer():
    """``exit_on_close`` counts the pages by their connections: viser counts a page as a client only
    once its first camera message has come and runs no client callback for one that closes
    before (a page closed at once on a loaded machine: the command then never exited). Here a
    connection that says viser's protocol and closes at once, without a browser: the viewer
    serves until it closes, then stops."""
    from websockets.sync.client import connect

    viewer = Viewer(press_scene(), port=free_port(), playing=False)
    try:
        viewer.exit_on_close()
        assert not viewer._stop.wait(0.5)  # no page yet: serving
        with connect(f"ws://127.0.0.1:{viewer.port}", subprotocols=[f"viser-v{viser.__version__}"]):
            time.sleep(0.2)
            assert not viewer._stop.is_set()  # a page open
        assert viewer._stop.wait(10)  # closed before any camera message: stopped
    finally:
        viewer.close()


def test_actions_without_a_browser(tmp_path):
    """The viewer's actions on a running simulation: playing runs steps and pauses at ``steps``,
    options and materials change it, reset starts again (keeping the material chosen), a cut of
    two rays across the block adds nodes, a node grabbed by a ray follows where it is dragged,
    colours and recorded frames."""
    scene = tm.load_scene(SCENES / "cut.toml")
    with Viewer(scene, port=free_port(), playing=True, steps=6, record=tmp_path / "rec") as viewer:
        viewer.wait_steps(6)
        time.sleep(0.2)
        assert viewer.sim.steps_done == 6 and not viewer.playing  # paused at steps
        viewer.set_options(dt=0.005)
        viewer.step(2)
        assert viewer.sim.options.dt == 0.005 and viewer.sim.time == pytest.approx(6 * 0.01 + 2 * 0.005)
        for coloring in ("stress", "none", "displacement"):
            viewer.set_coloring(coloring)
        with pytest.raises(tm.SceneError, match="coloring must be one of"):
            viewer.set_coloring("temperature")
        x = viewer.sim.positions(0)
        low, high = x.min(0).values, x.max(0).values
        middle = 0.5 * (low + high)
        above = float(high[2]) + 1.0
        # two vertical rays through the block's middle, from one side to the other
        added = viewer.cut(((float(middle[0]), float(low[1]) - 0.1, above), (0, 0, -1)),
                           ((float(middle[0]), float(high[1]) + 0.1, above), (0, 0, -1)))
        assert added > 0 and viewer.sim.mesh(0).num_vertices > x.shape[0]
        # grab the node under a ray straight down onto the block's top, drag it up, let it go
        body, node = viewer.grab(((float(low[0]) + 0.01, float(middle[1]), above), (0.0, 0.0, -1.0)))
        lifted = viewer.sim.positions(body)[node] + torch.tensor([0.0, 0.0, 0.05], dtype=x.dtype)
        viewer.drag(lifted.tolist())
        viewer.step(2)
        torch.testing.assert_close(viewer.sim.positions(body)[node], lifted, rtol=0, atol=1e-6)
        viewer.release()
        assert viewer.sim._held is None and viewer._drag_gizmo is None
        with pytest.raises(tm.SceneError, match="no node is grabbed"):
            viewer.drag((0.0, 0.0, 0.0))
        old = viewer.sim
        viewer.set_material(model="hooke", young=2e6)
        assert viewer.sim is not old and viewer.sim.steps_done == 0
        assert viewer.sim.bodies[0].material.model == "hooke" and viewer.sim.bodies[0].material.young == 2e6
        viewer.step(1)
        viewer.reset()  # the initial state, with the material chosen
        assert viewer.sim.steps_done == 0 and viewer.sim.bodies[0].material.model == "hooke"
        assert viewer.sim.mesh(0).num_vertices == x.shape[0]
    frames = sorted((tmp_path / "rec").glob("*.vtu"))
    assert frames and (tmp_path / "rec" / f"{scene.name}.pvd").is_file()


def test_stress_colour_is_the_stvk_stress():
    """nodal_von_mises: zero at rest and under a rigid rotation; a uniaxial stretch of a cube's
    tetrahedra gives each the von Mises norm of S = lam tr(E) I + 2 mu E."""
    from tensormass_torch.mesh.geometry import shape_vectors

    mesh = tm.beam_mesh(1, 1, 1, size=(1.0, 1.0, 1.0), dtype=torch.float64)
    m, _ = shape_vectors(mesh.vertices[mesh.elements])
    n = mesh.num_elements
    lam, mu = torch.full((n,), 2.0, dtype=torch.float64), torch.full((n,), 1.0, dtype=torch.float64)
    assert float(nodal_von_mises(mesh.vertices, mesh.elements, m, lam, mu).abs().max()) < 1e-12
    turn = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert float(nodal_von_mises(mesh.vertices @ turn.T, mesh.elements, m, lam, mu).abs().max()) < 1e-12
    stretch = mesh.vertices * torch.tensor([1.1, 1.0, 1.0], dtype=torch.float64)
    e = 0.5 * (1.1 ** 2 - 1.0)
    s = torch.diag(torch.tensor([2 * e + 2 * e, 2 * e, 2 * e], dtype=torch.float64))  # lam tr(E) + 2 mu E
    dev = s - s.trace() / 3 * torch.eye(3, dtype=torch.float64)
    expected = float(torch.sqrt(1.5 * (dev * dev).sum()))
    torch.testing.assert_close(nodal_von_mises(stretch, mesh.elements, m, lam, mu),
                               torch.full((mesh.num_vertices,), expected, dtype=torch.float64))


def test_bad_input_gives_one_clear_error(tmp_path, capsys):
    from tensormass_torch.app.cli import main

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        with pytest.raises(ViewerError, match=f"cannot serve on 127.0.0.1:{port}.*in use.*--port"):
            Viewer(press_scene(), port=port)
        assert main(["view", str(SCENES / "press.toml"), "--port", str(port)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("tensormass: error: cannot serve on")
    assert main(["view", "no_such_scene"]) == 2
    assert "unknown scene 'no_such_scene'" in capsys.readouterr().err
    assert main(["view", str(tmp_path / "missing.toml")]) == 1
    assert "missing.toml" in capsys.readouterr().err
    with pytest.raises(tm.SceneError, match="expected a tm.Simulator or a scene"):
        Viewer("press", port=free_port())
    with pytest.raises(tm.SceneError, match="coloring must be one of"):
        Viewer(press_scene(), port=free_port(), coloring="heat")
    with pytest.raises(ViewerError, match="port must be an integer"):
        Viewer(press_scene(), port=70000)
