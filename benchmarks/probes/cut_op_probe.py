"""cutting_cut_mesh alone, on the host: the SOFA beam cut along a strip, every element alive
against only those near the blade (``ops.cutting.near_elements``), with torch's threads and one.

    python benchmarks/probes/cut_op_probe.py
"""
import time

import torch

import tensormass_torch as tm
from tensormass_torch.ops import cutting, library
from tensormass_torch.sim import builtin


def main():
    mesh = builtin.sofa_beam(model="hooke", device="cpu").simulator.bodies[0].mesh
    library.ensure_registered()
    op = torch.ops.tensormass.cutting_cut_mesh
    blade = tm.Blade.swept((9.55, 8.0, -3), (9.55, 8.0, 3), (9.55, 7.73, -3), (9.55, 7.73, 3))
    near = cutting.near_elements(mesh.elements, mesh.vertices, blade)
    args = (mesh.vertices, blade.vertices.to(mesh.vertices.dtype), blade.triangles.long(),
            torch.zeros((0, 2), dtype=torch.long))
    every = torch.ones(mesh.elements.shape[0], dtype=torch.bool)
    for threads in (torch.get_num_threads(), 1):
        torch.set_num_threads(threads)
        for name, alive in (("all", every), ("near", near)):
            times = []
            for _ in range(7):
                start = time.perf_counter()
                op(mesh.elements, alive, *args)
                times.append(time.perf_counter() - start)
            times.sort()
            print(f"threads {threads} {name} ({int(alive.sum())} alive): op ms min {1e3 * times[0]:.3f} "
                  f"median {1e3 * times[3]:.3f}")


if __name__ == "__main__":
    main()
