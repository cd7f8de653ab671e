"""Argument types and the help formatter shared by every command (each rule written once)."""

from __future__ import annotations

import argparse

import numpy as np

from .._validation import as_depth_range

__all__ = ["Formatter", "positive_int", "nonneg_float", "tol_arg", "depth", "ratio_arg", "parse_point",
           "depth_range_arg", "add_verbosity", "bounded_int", "max_features_arg", "seed_arg", "image_file_arg",
           "not_an_input"]


class Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, except None, the False of on/off flags, and defaults the help states."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or "default:" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def _number(text: str, what: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None


def positive_int(text):
    """An integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def bounded_int(lo: int, hi: int):
    """An argparse type: an integer in ``[lo, hi]`` (the option's name is added by argparse)."""
    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer in [{lo}, {hi}], got {text!r}") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"expected an integer in [{lo}, {hi}], got {text!r}")
        return v
    parse.__name__ = f"integer in [{lo}, {hi}]"
    return parse


#: ``--max-features``: at most OpenCV's int.
max_features_arg = bounded_int(1, 2**31 - 1)
#: A seed for numpy's generator.
seed_arg = bounded_int(0, 2**63 - 1)


def image_file_arg(text):
    """A figure path with an extension OpenCV can write."""
    import cv2

    if not cv2.haveImageWriter(text):
        raise argparse.ArgumentTypeError(f"OpenCV cannot write the extension of {text!r} (use .png, .jpg, .tif, ...)")
    return text


def nonneg_float(text):
    """A finite number >= 0."""
    v = _number(text, "a number")
    if not np.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return v


def tol_arg(text):
    """A pixel tolerance (a finite number >= 0) or ``auto``."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return nonneg_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a finite number of pixels >= 0 or 'auto', got {text!r}") from None


def depth(text):
    """A depth >= 0 (inf allowed)."""
    v = _number(text, "a depth (number or inf)")
    if np.isnan(v) or v < 0:
        raise argparse.ArgumentTypeError(f"expected a depth >= 0, got {text!r}")
    return v


def ratio_arg(text):
    """A ratio in (0, 1]."""
    v = nonneg_float(text)
    if not 0 < v <= 1:
        raise argparse.ArgumentTypeError(f"expected a ratio in (0, 1], got {text!r}")
    return v


def parse_point(text: str) -> tuple[float, float]:
    """``x,y`` in pixels."""
    try:
        x, y = (float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a point must be written x,y (e.g. 120.5,80), got {text!r}") from None
    if not (np.isfinite(x) and np.isfinite(y)):
        raise argparse.ArgumentTypeError(f"a point must be finite, got {text!r}")
    return x, y


def depth_range_arg(values) -> tuple[float, float]:
    """``--depth-range ZMIN ZMAX`` (two parsed depths, or None for ``(0, inf)``), checked as a pair."""
    if values is None:
        return (0.0, np.inf)
    zmin, zmax = values
    as_depth_range((zmin, zmax), None, "--depth-range")
    return (zmin, zmax)


def add_verbosity(parser: argparse.ArgumentParser) -> None:
    """``-q`` / ``--quiet`` and ``-v`` / ``--verbose``, exclusive.

    Added to the main parser and to every command, so that they work before or after the
    command's name; with no default (``SUPPRESS``), a command's parser does not reset a value
    the main parser set.
    """
    g = parser.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="print nothing but errors")
    g.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                   help="more detail on stderr (settings, repairs of rounded calibrations, timings)")


def not_an_input(output, inputs, option: str) -> None:
    """Refuse (``UserError``-like ``ValueError``) an output path that is one of the input files."""
    from pathlib import Path

    if output is None:
        return
    out = Path(output)
    for p in inputs:
        if p is not None and out.exists() and Path(p).exists() and out.resolve() == Path(p).resolve():
            raise ValueError(f"{option} {str(output)!r} is an input file of this command; writing it would replace it: "
                             "give another path")
