"""A command line's exit status, whether its ``main`` returns it or argparse exits with it."""

from __future__ import annotations

from collections.abc import Callable, Sequence


def exit_status(main: Callable[[Sequence[str]], int], argv: Sequence[str]) -> int:
    """``main(argv)``'s return value, or the status of the ``SystemExit`` it raised (argparse's
    refusal of a flag's value exits with 2)."""
    try:
        return main(list(argv))
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else 1
