"""The paper's Figure 1: one clamped beam under gravity, linear (hooke) against St Venant-Kirchhoff
(stvk), and the rest shape, side by side.

    python examples/figure1.py [--cells 2] [--young 1e6] [--out out/figure1]

Static equilibrium of a soft 1 m x 0.1 m x 0.1 m beam clamped at x = 0. Linear elasticity has
no geometric non-linearity: every point falls straight down and the beam stretches to keep up
(its tip drops further and never moves toward the wall). St Venant-Kirchhoff measures the Green
strain, so the beam keeps its length and curls in toward the wall. Writes ``figure1.png`` (via
pyvista, when installed) and the three shapes as ``.vtu`` files; returns the tip displacements.
"""
import argparse
from pathlib import Path

import torch

import tensormass_torch as tm

LENGTH, SIDE = 1.0, 0.1


def solve(model_name, cells, young, dtype):
    """Static displacement ``[V, 3]`` of the clamped beam with material model ``model_name``."""
    mesh = tm.beam_mesh(10 * cells, cells, cells, size=(LENGTH, SIDE, SIDE), dtype=dtype)
    material = tm.Material(young=young, poisson=0.3, density=1000.0, model=model_name)
    model = tm.TensorMass(mesh, material)
    u = tm.solve_static(model, fixed=mesh.vertices[:, 0] <= 1e-9, gravity=(0.0, 0.0, -9.81), tol=1e-6,
                        max_newton=100)
    return mesh, u


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=2, help="cells across the section (10x along the beam)")
    parser.add_argument("--young", type=float, default=1e6, help="Young's modulus in Pa (softer bends more)")
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    parser.add_argument("--out", default="out/figure1", help="folder for figure1.png and the .vtu files")
    parser.add_argument("--no-render", action="store_true", help="write only the .vtu files")
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    out = Path(args.out)

    shapes, tips = {}, {}
    for name in ("hooke", "stvk"):
        mesh, u = solve(name, args.cells, args.young, dtype)
        tip = mesh.vertices[:, 0] >= LENGTH - 1e-9
        tips[name] = u[tip].mean(dim=0)
        shapes[name] = mesh.vertices + u
        print(f"{name:5s}: tip displacement x {tips[name][0]:+.4f} m, z {tips[name][2]:+.4f} m")

    files = [out / "figure1_rest.vtu", out / "figure1_hooke.vtu", out / "figure1_stvk.vtu"]
    tm.save_mesh(files[0], mesh)
    for name, file in zip(("hooke", "stvk"), files[1:]):
        tm.save_mesh(file, tm.TetMesh(shapes[name], mesh.elements), displacement=shapes[name] - mesh.vertices)
    if not args.no_render:
        try:
            from tensormass_torch.app.render import render_png

            files.append(render_png(out / "figure1.png",
                                    [[(mesh, shapes["hooke"])], [(mesh, shapes["stvk"])], [(mesh, None)]],
                                    labels=["hooke (linear)", "stvk (St Venant-Kirchhoff)", "rest shape"],
                                    camera="xz", window_size=(1500, 500)))
        except ImportError as exc:  # pyvista is optional: the .vtu files open in ParaView
            print(f"no picture: {exc}")
    print("wrote " + ", ".join(str(f) for f in files))
    return {"tips": tips, "files": files}


if __name__ == "__main__":
    main()
