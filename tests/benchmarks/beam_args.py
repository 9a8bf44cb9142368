"""Command-line options shared by the beam benchmarks (bench_forward, bench_gradient).

Imported before DOLFINx: ``--cold`` must set the FFCx cache location before the first import.
"""

import argparse

__all__ = ["beam_parser"]


def beam_parser(description: str, steps: int) -> argparse.ArgumentParser:
    """A parser with the beam's box cells, BDF2 steps, time step and ``--cold``."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--cells", type=int, nargs=3, default=[80, 10, 10], help="box cells")
    p.add_argument("--steps", type=int, default=steps, help="BDF2 steps")
    p.add_argument("--dt", type=float, default=0.01, help="time step")
    p.add_argument("--cold", action="store_true", help="compile into an empty FFCx cache first")
    return p
