"""The CG's fused steps under body contact against the paths they replaced, in one process: two
simulators of the same pile from the same state, stepped in alternated blocks, one of them with
the old path put back while it steps (rates of separate processes differ by 10-15 %).

    python benchmarks/probes/cg_fusions_probe.py --change alpha_dot|accumulate|block_jacobi|coarse_direction
                                                 [--columns 10]
                                                 [--shift 0.01] [--steps 120] [--state DIR]
                                                 [--contact '{"friction": 0.5}']
                                                 [--preconditioner auto] [--timed 10]
                                                 [--repeats 4] [--out fusions.json] [--device cuda]

``--change``:
    alpha_dot    the step length of a product without its dots in one op (``ops.cg.cg_alpha_dot``)
                 against the projection, the per-node dots and ``cg_alpha``;
    accumulate   the pairs' product added to the fused product's output in place
                 (``contact_pair_product``'s accumulate) against its own output plus an add;
    block_jacobi block Jacobi applied inside the CG's update (``preconditioner.BlockJacobi``)
                 against CG on the scaled system S^T A S (``JacobiScaling``: two block products
                 an iteration);
    coarse_direction  the rigid correction's coarse part added by the CG's direction, r.z from the
                 coarse vectors (``cg_coarse_beta``), against the prolongation adding it to z and
                 r.z over the nodes (``cg_dot_beta``) (with ``--preconditioner rigid``).

The pile is ``contact_piles``' (``pile_arguments``), stepped ``--steps`` steps with ``--contact``
or taken from ``--state``. For each block: ms a step and CG iterations a step (the accumulate is
exact: the same iterations; the dots of alpha_dot, block_jacobi's and coarse_direction's r.z are
summed in another order).
"""
import contextlib
import sys
from pathlib import Path
from unittest import mock

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import contact_piles  # noqa: E402
from contact_settings_probe import block  # noqa: E402

import tensormass_torch as tm  # noqa: E402
from tensormass_torch.ops import cg as cg_ops  # noqa: E402
from tensormass_torch.physics import body_contact  # noqa: E402
from tensormass_torch.solver import implicit_euler  # noqa: E402
from tensormass_torch.solver.cg import CGSolver  # noqa: E402
from tensormass_torch.solver.preconditioner import JacobiScaling  # noqa: E402

CHANGES = ("alpha_dot", "accumulate", "block_jacobi", "coarse_direction")


def _own_output_then_add(kept):
    def pair_product(*args, add_to=None, **kwargs):  # its own output, then the sum
        out = kept(*args, **kwargs)
        return out if add_to is None else add_to + out

    return pair_product


def _corrected_z_iterate(self, matvec, max_iter, preconditioner):
    """The block iteration as it was before the direction took the coarse part: z += w Z' E^-1 Z'^T r
    (``correct``, the prolongation op), r.z over the nodes (``pcg_beta``), p = z + beta p."""
    s, b = self.state, self._block_buffers()
    step = self._pcg_buffers().scaled
    fused = getattr(matvec, "matvec_alpha", None) if self.native is not None else None
    ap = fused(s.p, self.plan, step) if fused is not None else None
    if ap is None:
        ap = self._step_length(matvec, step)
    cg_ops.cg_update(ap, self.plan, s, max_iter, self.native, preconditioner.inverse_blocks, b.z)
    preconditioner.correct(s.r, b.z)
    cg_ops.pcg_beta(s.r, b.z, self.plan, self._pcg_buffers().rz, s, self.native)
    cg_ops.cg_direction(self.plan, b.direction, self.native)


def old_path(change: str):
    """The path ``change`` replaced, put back for a ``with`` (and taken out again after it)."""
    if change == "alpha_dot":
        return mock.patch.object(CGSolver, "_projects_in_one_op", lambda self, out: False)
    if change == "accumulate":
        return mock.patch.object(body_contact.contact_ops, "pair_product",
                                 _own_output_then_add(body_contact.contact_ops.pair_product))
    if change == "coarse_direction":
        kept = CGSolver._block_iterate

        def block_iterate(self, matvec, max_iter, preconditioner):
            if getattr(preconditioner, "coarse_terms", None) is None:
                return kept(self, matvec, max_iter, preconditioner)
            return _corrected_z_iterate(self, matvec, max_iter, preconditioner)

        return mock.patch.object(CGSolver, "_block_iterate", block_iterate)
    # block_jacobi: a system made while it is in place keeps the scaled system's JacobiScaling
    return mock.patch.object(implicit_euler, "BlockJacobi", JacobiScaling)


def extend(parser):
    parser.add_argument("--change", choices=CHANGES, required=True)
    parser.add_argument("--preconditioner", default="auto")
    parser.add_argument("--repeats", type=int, default=4, help="blocks of --timed steps for each path")
    parser.add_argument("--out", default=None, help="a JSON file for the blocks' figures")


def main(argv=None):
    args = contact_piles.pile_arguments(argv, __doc__, timed=10, extend=extend)
    dtype = torch.float32
    bodies, x, v = contact_piles.pile_start(args, dtype)
    sims = {}
    for name in ("old", "new"):
        sim = contact_piles.simulator(bodies, tm.Contact(**args.contact), args.device, dtype, args.preconditioner)
        sim.x, sim.v = x.clone(), v.clone()
        with old_path(args.change) if name == "old" else contextlib.nullcontext():
            sim.step(2)
        sims[name] = sim
    blocks = {name: [] for name in sims}
    for _ in range(args.repeats):
        for name, sim in sims.items():
            with old_path(args.change) if name == "old" else contextlib.nullcontext():
                blocks[name].append(block(sim, args.timed, args.device))
    print(f"{len(bodies)} blocks, --change {args.change}, --preconditioner {args.preconditioner}; "
          f"ms a step / CG iterations a step, {args.repeats} blocks of {args.timed} steps each:")
    for name, runs in blocks.items():
        print(f"  {name:4s} " + "   ".join(f"{r['ms']:6.1f} / {r['iterations']:5.1f}" for r in runs))
    common.write_blocks(args.out, args, blocks)
    return blocks


if __name__ == "__main__":
    main()
