"""What the live viewer costs the simulation: steps/s of a scene stepping alone against the same
scene playing in a ``Viewer`` with a page connected (a headless Chromium, software WebGL), per
colouring, in one process.

    python benchmarks/studies/viewer_overhead.py --device cuda --out DIR
    ... --quick                                   # a small beam, seconds on a CPU

The scene is SOFA's beam (101,250 tets, hooke, 10 CG iterations a step; ``--scale 5``: a coarser
one). "alone": ``sim.step(n)`` in a loop for ``--seconds``, n of ``--chunks`` (the fastest is the
reference); "viewer": a fresh simulator of the
scene playing in the viewer for as long, after a warm-up, its steps counted over that time
(the viewer batches steps to about 30 frames a second, draws each frame on a thread of its own
and skips frames while the last one is being drawn). ``--pages yes,no``: with a page connected (a
headless Chromium drawing with software WebGL, on the same CPU) and without one (the viewer's
own cost: copies, colours, encoding, messages); without a Chromium (or playwright) the "yes" runs
have no page either, which the table says. ``client``: a websocket client in this process (a
thread) that takes every message the viewer sends and draws nothing: the simulation's side of a
connected page (encoding and sending each frame) without a browser's drawing, which on a GPU
machine with a browser would run on other cores; it needs only viser's own ``websockets``.
"""
from __future__ import annotations

import argparse
import shutil
import socket
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common
import common
import torch
from common import Results, metadata, record

from tensormass_torch.sim.builtin import sofa_beam

COLUMNS = [("run", "run", None), ("coloring", "colour", None), ("page", "page", None),
           ("steps", "steps", None), ("seconds", "s", ".1f"), ("steps_per_s", "steps/s", ".1f"),
           ("relative", "x alone", ".3f"), ("frames", "frames", None), ("megabytes", "MB received", ".1f")]


def alone(scene_factory, seconds: float, device, chunk: int) -> dict:
    """``sim.step(chunk)`` in a loop: a call chains its steps with one host synchronisation on a
    GPU, so the viewer's long batches (hundreds of steps a frame there) are compared with calls
    of about their length as well as with short ones."""
    sim = scene_factory().simulator
    sim.step(3)
    common.sync(device)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        sim.step(chunk)
        steps += chunk
    common.sync(device)
    elapsed = time.perf_counter() - start
    return dict(run=f"alone, {chunk} steps a call", steps=steps, seconds=elapsed, steps_per_s=steps / elapsed)


class MessageClient:
    """A websocket client of the viewer's page protocol that receives and discards every message,
    on a thread of its own; ``received`` counts the bytes."""

    def __init__(self, url: str):
        import viser
        from websockets.sync.client import connect

        self.received = 0
        self._connection = connect(url.replace("http://", "ws://"), max_size=None,
                                   subprotocols=[f"viser-v{viser.__version__}"])
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self):
        from websockets.exceptions import ConnectionClosed

        try:
            while True:
                self.received += len(self._connection.recv())
        except ConnectionClosed:
            pass

    def close(self):
        self._connection.close()
        self._thread.join(timeout=10)


def in_viewer(scene_factory, seconds: float, coloring: str, page="yes") -> dict:
    from tensormass_torch.app.viewer import Viewer

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = Viewer(scene_factory(), port=port, coloring=coloring, playing=False)
    browser = playwright = client = None
    try:
        if page == "client":
            client = MessageClient(viewer.url)
        chromium = (shutil.which("chromium-headless-shell") or shutil.which("chromium")) if page == "yes" else None
        if chromium:
            try:
                from playwright.sync_api import sync_playwright

                playwright = sync_playwright().start()
                browser = playwright.chromium.launch(executable_path=chromium, args=[
                    "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
                page = browser.new_page(viewport={"width": 960, "height": 600})
                page.goto(viewer.url)
                page.get_by_text("Connected").wait_for(timeout=60_000)
            except ImportError:
                browser = None
        viewer.step(3)
        viewer.play()
        time.sleep(min(2.0, seconds / 3))  # the batch size settles
        first, start, frames = viewer.sim.steps_done, time.perf_counter(), viewer.frames
        time.sleep(seconds)
        steps, elapsed = viewer.sim.steps_done - first, time.perf_counter() - start
        viewer.pause()
        connected = "browser" if browser is not None else "client" if client is not None else "none"
        return dict(run="viewer", coloring=coloring, page=connected, steps=steps, seconds=elapsed,
                    steps_per_s=steps / elapsed, frames=viewer.frames - frames,
                    megabytes=client.received / 1e6 if client is not None else None)
    finally:
        if client is not None:
            client.close()
        viewer.close()
        if browser is not None:
            browser.close()
        if playwright is not None:
            playwright.stop()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--out", default="benchmarks/results/viewer")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--scale", type=int, default=None, help="SOFA beam coarsening (1: 101,250 tets)")
    parser.add_argument("--seconds", type=float, default=None, help="measured seconds per run")
    parser.add_argument("--colorings", default="displacement,none")
    parser.add_argument("--chunks", default="10,256",
                        help="steps per sim.step call of the runs alone; the fastest is the reference")
    parser.add_argument("--pages", default="yes,no",
                        help="runs with a page connected (yes: a headless Chromium), with a message client "
                             "that draws nothing (client), and without either (no: the viewer's own cost)")
    args = parser.parse_args(argv)
    common.fill_defaults(args, dict(scale=1, seconds=15.0), dict(scale=5, seconds=3.0))
    device = torch.device(args.device)

    def factory():
        return sofa_beam(model="hooke", device=device, scale=args.scale)

    elements = factory().simulator.model.num_elements
    results = Results(args.out, "viewer_overhead", "Steps/s of SOFA's beam alone and playing in the viewer",
                      metadata(device, elements=elements),
                      COLUMNS, notes=[f"SOFA beam, {elements} tets, hooke, 10 CG iterations, float32; "
                                      f"{args.seconds:g} s a run."])
    runs = [alone(factory, args.seconds, device, int(chunk)) for chunk in args.chunks.split(",")]
    base = max(runs, key=lambda run: run["steps_per_s"])
    for run in runs:
        results.add(record(**run, relative=run["steps_per_s"] / base["steps_per_s"]))
    for page in args.pages.split(","):
        for coloring in args.colorings.split(","):
            rec = in_viewer(factory, args.seconds, coloring, page)
            rec["relative"] = rec["steps_per_s"] / base["steps_per_s"]
            results.add(record(**rec))
    results.finish()


if __name__ == "__main__":
    main()
