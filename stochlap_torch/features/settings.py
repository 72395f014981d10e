"""What decides the numbers of :func:`~stochlap_torch.features.multiscale_features`, resolved.

Every entry point of the features (the function, :class:`~stochlap_torch.nn.MultiscaleFeatures`,
the dataset, the PyG transform, the cache) turns its arguments into one
:class:`FeatureSettings` with :func:`feature_settings`: defaults filled in, values checked and
spelled one way, and an option the chosen variant does not use refused. Equal settings are
equal objects with equal ``repr``, so they key a cache and mark a processed dataset alike.
"""

from __future__ import annotations

from dataclasses import dataclass

from .._common.checks import check_choice, refuse_unused
from .._common.errors import ParameterError
from .._common.variants import DEFAULT_FEATURE_VARIANT, FEATURE_VARIANTS, PAPER_FEATURE_SCALES
from ..diffusion.parameters import PaperParams, as_paper_params
from ..diffusion.robust import RobustParams, as_robust_params
from .paper import FEATURE_GROUPS, NORMALISATIONS, check_include, paper_channel_names
from .robust import robust_channel_names

__all__ = ["FeatureSettings", "feature_settings"]


@dataclass(frozen=True)
class FeatureSettings:
    """The resolved settings of the features: everything their numbers depend on.

    Attributes:
        variant: ``"robust"`` or ``"paper"``.
        params: :class:`~stochlap_torch.diffusion.RobustParams` or
            :class:`~stochlap_torch.diffusion.PaperParams`, per ``variant``.
        include: the paper's feature groups, in channel order (``None`` for ``"robust"``).
        rotation_invariant: the paper's coefficients in the vertex frame (``None`` for
            ``"robust"``, whose channels always are).
        normalisation: the paper's per-mesh length (``None`` for ``"robust"``).
    """

    variant: str
    params: RobustParams | PaperParams
    include: tuple[str, ...] | None = None
    rotation_invariant: bool | None = None
    normalisation: str | None = None

    def channel_names(self) -> list[str]:
        """The ``C`` names of the feature columns, in order."""
        if self.variant == "robust":
            return robust_channel_names(self.params)
        return paper_channel_names(self.params.num_scales, self.include, self.rotation_invariant)


def feature_settings(
    variant: str | None = None,
    num_scales: int | None = None,
    threshold: float | None = None,
    include: tuple[str, ...] | None = None,
    rotation_invariant: bool | None = None,
    normalisation: str | None = None,
    differentiable_operator: bool | None = None,
    robust: RobustParams | None = None,
    paper: PaperParams | None = None,
) -> FeatureSettings:
    """The :class:`FeatureSettings` of these arguments (those of
    :func:`~stochlap_torch.features.multiscale_features`; ``None`` is "not given").

    ``num_scales`` (and for ``"paper"`` ``threshold``) override the field of ``robust`` or
    ``paper``. ``differentiable_operator`` does not change the numbers and is only checked.

    Raises:
        ParameterError: a bad value, or an option the variant does not use (``"robust"``:
            ``threshold``, ``include``, ``rotation_invariant``, ``normalisation``,
            ``differentiable_operator``, ``paper``; ``"paper"``: ``robust``).
    """
    variant = check_choice(
        "variant", DEFAULT_FEATURE_VARIANT if variant is None else variant, FEATURE_VARIANTS
    )
    if variant == "robust":
        refuse_unused(
            variant,
            {
                "threshold": threshold,
                "include": include,
                "rotation_invariant": rotation_invariant,
                "normalisation": normalisation,
                "differentiable_operator": differentiable_operator,
                "paper": paper,
            },
        )
        return FeatureSettings(variant, as_robust_params(robust, num_scales))
    refuse_unused(variant, {"robust": robust})
    include = FEATURE_GROUPS if include is None else check_include(include)
    rotation_invariant = True if rotation_invariant is None else rotation_invariant
    if not isinstance(rotation_invariant, bool):
        raise ParameterError(
            f"rotation_invariant must be True or False, got {rotation_invariant!r}"
        )
    normalisation = "mean_edge" if normalisation is None else normalisation
    check_choice("normalisation", normalisation, NORMALISATIONS)
    if differentiable_operator is not None and not isinstance(differentiable_operator, bool):
        raise ParameterError(
            f"differentiable_operator must be True or False, got {differentiable_operator!r}"
        )
    return FeatureSettings(
        variant,
        as_paper_params(paper, num_scales, threshold, PAPER_FEATURE_SCALES),
        # In channel order: the groups always come in that order, however they were listed.
        tuple(group for group in FEATURE_GROUPS if group in include),
        rotation_invariant,
        normalisation,
    )
