"""cutting_cut_mesh alone, on the host: the SOFA beam cut along a strip, every element alive
against only those near the blade (``ops.cutting.near_elements``), with torch's threads and one.

    python benchmarks/probes/cut_op_probe.py
"""
import time, torch
import tensormass_torch as tm
from tensormass_torch.sim import builtin
from tensormass_torch.ops import library, cutting as oc
scene = builtin.sofa_beam(model="hooke", device="cpu")
b = scene.simulator.bodies[0]
v = b.mesh.vertices; el = b.mesh.elements
library.ensure_registered()
op = torch.ops.tensormass.cutting_cut_mesh
blade = tm.Blade.swept((9.55, 8.0, -3), (9.55, 8.0, 3), (9.55, 7.73, -3), (9.55, 7.73, 3))
near = oc.near_elements(el, v, blade)
bv, bt = blade.vertices.to(v.dtype), blade.triangles.long()
slit = torch.zeros((0, 2), dtype=torch.long)
alive = torch.ones(el.shape[0], dtype=torch.bool)
for threads in (torch.get_num_threads(), 1):
    torch.set_num_threads(threads)
    for name, a in (("all", alive), ("near", near)):
        ts = []
        for k in range(7):
            t = time.perf_counter(); op(el, a, v, bv, bt, slit); ts.append(time.perf_counter() - t)
        print(f"threads {threads} {name} ({int(a.sum())} alive): op ms min {1e3*min(ts):.3f} median {1e3*sorted(ts)[3]:.3f}")
