"""The names of the variants, importable without torch (the command line lists them)."""

from __future__ import annotations

__all__ = ["DEFAULT_FEATURE_VARIANT", "DEFAULT_VARIANT", "FEATURE_VARIANTS", "VARIANTS"]

#: Saliency variants: ``"robust"`` (its own representation, :mod:`stochlap_torch.diffusion.
#: robust`) and the paper's Algorithm 2 with the variants built on its representation.
VARIANTS = ("robust", "paper", "normal_coefficients", "normal_displacement", "valence_normalised")
#: The saliency every entry point computes unless told otherwise: the robust one, the same for
#: the same surface meshed twice (rank correlation 0.91-0.95 under decimation and remeshing,
#: against 0.07-0.23 for the paper's; ``benchmarks/robust.py``).
DEFAULT_VARIANT = "robust"
#: Representations the features can come from.
FEATURE_VARIANTS = ("robust", "paper")
#: The features' default: the robust channels (the paper's have a mean per-channel rank
#: correlation of 0.2 between two meshings of one surface).
DEFAULT_FEATURE_VARIANT = "robust"
