"""The ``tensormass`` command line (also ``python -m tensormass_torch``).

    tensormass info          backend report (tm.backend_info()) as JSON
"""
import argparse
import json
import sys


def _cmd_info(args):
    from ._backend import backend_info

    print(json.dumps(backend_info(), indent=2))
    return 0


def build_parser():
    parser = argparse.ArgumentParser(
        prog="tensormass",
        description="Tensor-Mass soft-body simulation with an implicit solver (PyTorch).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    info = sub.add_parser("info", help="print the backend report (tm.backend_info()) as JSON")
    info.set_defaults(func=_cmd_info)
    return parser


def main(argv=None):
    """Entry point of the ``tensormass`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    from ._backend import BackendError

    try:
        return args.func(args)
    except BackendError as exc:  # e.g. a bad TENSORMASS_BACKEND value
        print("tensormass: error: %s" % exc, file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
