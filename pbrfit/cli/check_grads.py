"""`pbrfit check-grads`: every BRDF term's autodiff gradient against finite differences
(`pbrfit.checks.gradcheck`)."""

from __future__ import annotations

from .parser import EXIT_FAILED, EXIT_OK
from ..checks import gradcheck

__all__ = ["run"]


def run(args) -> int:
    """`pbrfit check-grads` on its parsed arguments: 0 where every check passes, else 1."""
    results = gradcheck.run_checks()
    ok = gradcheck.print_report(results, quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED
