"""Whether an answer meets the request's ``min_confidence``, and why not in a sentence: the one
rule behind ``accepted`` and ``reason`` over HTTP and gRPC."""

from __future__ import annotations


def acceptance(confidence: float | None, min_confidence: float | None) -> tuple[bool, str | None]:
    """Whether an answer of ``confidence`` meets the request's ``min_confidence``, and if not,
    why, in a sentence: the one rule behind ``accepted`` and ``reason`` over HTTP and gRPC.

    Without ``min_confidence`` every answer is accepted; with it, an answer whose confidence is
    below it, or unknown (weights without a calibrator), is not.
    """
    if min_confidence is None:
        return True, None
    if confidence is None:
        return False, (
            "this server's weights have no confidence calibrator, so min_confidence "
            f"{_number(min_confidence)} cannot be met"
        )
    if confidence < min_confidence:
        return False, (
            f"confidence {_below(confidence, min_confidence)} is below min_confidence "
            f"{_number(min_confidence)}: ask for another view"
        )
    return True, None


def _number(value: float) -> str:
    """Two decimals when that is exact (``0.80``), else the shortest exact form."""
    shown = f"{value:.2f}"
    return shown if float(shown) == value else repr(value)


def _below(value: float, limit: float) -> str:
    """``value`` with two decimals, or as many more as it takes to read below ``limit``."""
    for digits in range(2, 10):
        shown = f"{value:.{digits}f}"
        if float(shown) < limit:
            return shown
    return repr(value)
