"""Each method's options, declared once, with their defaults and checks.

* :class:`PaperParams`: the paper's operator (Algorithm 1) and saliency (Algorithm 2);
* :class:`PaperFeatureParams`: the paper's per-vertex features (its operator, plus which
  channels and how they are normalised);
* :class:`RobustParams`: the robust variant (heat diffusion on a mesh pyramid).

Every entry point (functions, layers, datasets, the PyG transform, the caches, the CLI) takes
its method's options as keywords and hands them to :func:`resolve_params`, which builds the
dataclass: adding an option to a method means adding a field here and nothing else. Equal
options give equal, hashable objects with an equal ``repr``, which key caches. Importing this
module does not import torch (the command line reads the defaults for its help).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

from ._common.checks import check_bool, check_choice, check_int, check_number, refuse_unused
from ._common.errors import ParameterError

__all__ = [
    "FEATURE_GROUPS",
    "MAX_SCALES",
    "NORMALISATIONS",
    "PaperFeatureParams",
    "PaperParams",
    "RobustParams",
    "method_of",
    "resolve_params",
]

#: More scales than this is a mistake (each scale at least doubles the diffusion time).
MAX_SCALES = 64
#: The paper features' channel groups, in channel order.
FEATURE_GROUPS = ("coefficients", "norms", "differences", "saliency")
#: Per-mesh lengths the paper features' coefficients are divided by (``"none"``: mesh units).
NORMALISATIONS = ("mean_edge", "bbox_diagonal", "none")


def _set(params, **values) -> None:
    """Store checked values on a frozen dataclass, as Python numbers: equal settings then
    compare, hash, print and key a cache equal whatever type they were spelled in."""
    for name, value in values.items():
        object.__setattr__(params, name, value)


@dataclass(frozen=True)
class PaperParams:
    """The paper's method: the stochastic mesh Laplacian multiplied up scale by scale.

    Attributes:
        num_scales: ``K`` in ``[2, 64]`` scales; scale 1 is the input (default 8, the
            paper's).
        threshold: ``lambda`` in ``(0, 1)``: entries of ``F^(k)`` below it are dropped and the
            rows re-normalised (default ``1e-3``).

    Raises:
        ParameterError: a value out of range (checked at construction).
    """

    num_scales: int = 8
    threshold: float = 1e-3

    def __post_init__(self) -> None:
        _set(
            self,
            num_scales=check_int("num_scales", self.num_scales, minimum=2, maximum=MAX_SCALES),
            threshold=check_number(
                "threshold", self.threshold, 0.0, 1.0, open_low=True, open_high=True
            ),
        )


@dataclass(frozen=True)
class PaperFeatureParams(PaperParams):
    """The paper's per-vertex features: :class:`PaperParams` (6 scales by default: each scale
    adds channels) and the channels' options.

    Attributes:
        include: a non-empty subset of :data:`FEATURE_GROUPS` (default: all), kept in channel
            order however it is listed.
        rotation_invariant: coefficients as (normal component, tangential norm) instead of
            xyz (default ``True``).
        normalisation: the per-mesh length coefficients are divided by, one of
            :data:`NORMALISATIONS` (default ``"mean_edge"``).
        differentiable_operator: gradients also flow through the operators (default
            ``False``: they are held constant). Changes the gradient, not the values.
    """

    num_scales: int = 6
    include: tuple[str, ...] = FEATURE_GROUPS
    rotation_invariant: bool = True
    normalisation: str = "mean_edge"
    differentiable_operator: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        include = (self.include,) if isinstance(self.include, str) else self.include
        try:
            include = tuple(include)
        except TypeError:
            include = None
        if not include or not set(include) <= set(FEATURE_GROUPS):
            raise ParameterError(
                f"include must be a non-empty subset of {FEATURE_GROUPS}, got {self.include!r}"
            )
        for name in ("rotation_invariant", "differentiable_operator"):
            check_bool(name, getattr(self, name))
        check_choice("normalisation", self.normalisation, NORMALISATIONS)
        _set(self, include=tuple(group for group in FEATURE_GROUPS if group in include))


#: ``RobustParams`` fields that are positive numbers, with the largest value that makes sense
#: (beyond it a product of them overflows, or the series they truncate is cut to nothing).
_ROBUST_NUMBERS = {
    "t0": 1.0,
    "resolution": 1e6,
    "fidelity": 1e6,
    "cap": 1e6,
    "clamp": 1e6,
    "tolerance": 1e-2,
    "heat_from": 1e6,
    "twist_from": 1e6,
    "heat_resolution": 1e6,
}
#: The smallest finest scale: below it the diffusion time underflows against the area.
_MIN_T0 = 1e-12


@dataclass(frozen=True)
class RobustParams:
    """The robust variant: heat diffusion for physical times on a pyramid of the mesh.

    Attributes:
        num_scales: scales ``t_k = t0 2^k A``, ``k = 0..num_scales-1``, in ``[1, 16]``
            (default 7).
        t0: the finest scale, as a fraction of the surface area ``A``, in ``[1e-12, 1]``
            (default ``1e-3``).
        resolution: a level carries scale ``t`` if its mean vertex area is ``<= t /
            resolution`` (a scale spans at least this many vertices; default 8).
        fidelity: ... and if its surface is within ``fidelity sqrt(t)`` of the mesh (default
            0.1).
        ratio: vertex-count ratio between pyramid levels, ``> 1`` (default 4).
        min_vertices: no pyramid level smaller than about this, ``>= 4`` (default 1000).
        cap: mass cap of the heat operator, in median stiffnesses (default 8).
        clamp: largest edge rate of the heat operator, in median rates, applied before the
            mass cap (default 32).
        tolerance: Chebyshev truncation of the semigroup, in ``(0, 1e-2]`` (default ``1e-6``).
        heat_from: the ``heat`` channel is computed for scales ``t >= heat_from A`` (default
            0.032).
        heat_resolution: vertex areas per scale the ``heat`` channel's level must resolve
            (default 16).
        twist_from: the ``twist`` channel is computed between consecutive scales ``t_k,
            t_(k+1)`` with ``t_k >= twist_from A`` (default 0.008: at finer scales the
            displacement's tangential part is the triangulation's, and its turn is noise).
        normal_time: ``dn``'s normal is the mesh's outward vertex normal diffused for a time
            ``normal_time A``, in ``[0, 1]`` (default ``2e-3``: twice the finest scale's
            ``t0``, so that it is the surface's normal, not its triangles'), plus a quarter of
            it diffused for a sixteenth of that time (thin parts, where the first cancels).

    Every number field but ``num_scales``, ``min_vertices`` and ``normal_time`` is positive;
    each has an upper bound past which the computation would overflow or be meaningless.

    Raises:
        ParameterError: a value out of range (checked at construction).
    """

    num_scales: int = 7
    t0: float = 1e-3
    resolution: float = 8.0
    fidelity: float = 0.1
    ratio: float = 4.0
    min_vertices: int = 1000
    cap: float = 8.0
    clamp: float = 32.0
    tolerance: float = 1e-6
    heat_from: float = 0.032
    heat_resolution: float = 16.0
    twist_from: float = 0.008
    normal_time: float = 2e-3

    def __post_init__(self) -> None:
        numbers = {
            name: check_number(name, getattr(self, name), 0.0, high, open_low=True)
            for name, high in _ROBUST_NUMBERS.items()
        }
        if numbers["t0"] < _MIN_T0:
            raise ParameterError(f"t0 must lie in [{_MIN_T0:g}, 1], got {numbers['t0']!r}")
        _set(
            self,
            num_scales=check_int("num_scales", self.num_scales, minimum=1, maximum=16),
            min_vertices=check_int("min_vertices", self.min_vertices, minimum=4, maximum=2**40),
            normal_time=check_number("normal_time", self.normal_time, 0.0, 1.0),
            ratio=check_number("ratio", self.ratio, 1.0, 1e6, open_low=True),
            **numbers,
        )

    @property
    def times(self) -> list[float]:
        """The scales ``t_k / A``."""
        return [self.t0 * 2.0**k for k in range(self.num_scales)]

    @property
    def heat_scales(self) -> list[int]:
        """The scales ``k`` the ``heat`` channel is computed at: ``t_k >= heat_from A``."""
        return [k for k, t in enumerate(self.times) if t >= self.heat_from]

    @property
    def twist_scales(self) -> list[int]:
        """The scales ``k`` the ``twist`` channel turns from (to ``k + 1``): ``t_k >= twist_from
        A``, ``k < num_scales - 1``."""
        return [k for k, t in enumerate(self.times[:-1]) if t >= self.twist_from]


def method_of(params, default: str = "robust") -> str:
    """The method ``params`` holds the options of: ``"paper"`` for a :class:`PaperParams`
    (:class:`PaperFeatureParams` included), ``"robust"`` for a :class:`RobustParams`, else
    ``default`` (a call given no options object takes its default method)."""
    if isinstance(params, PaperParams):
        return "paper"
    return "robust" if isinstance(params, RobustParams) else default


def _field_names(cls) -> list[str]:
    return [field.name for field in dataclasses.fields(cls)]


def _as_params(cls, value, name: str):
    """``value`` (an instance of ``cls``, of a parent of ``cls`` whose fields it takes, or a
    mapping of ``cls``'s fields) as ``cls``."""
    if isinstance(value, cls):
        return value
    if isinstance(value, Mapping):
        fields = dict(value)
    elif dataclasses.is_dataclass(value) and issubclass(cls, type(value)):
        fields = {field: getattr(value, field) for field in _field_names(type(value))}
    else:
        raise ParameterError(
            f"{name} must be a {cls.__name__} (or a mapping of its fields), got "
            f"{type(value).__name__}"
        )
    unknown = sorted(set(map(str, fields)) - set(_field_names(cls)))
    if unknown:
        raise ParameterError(
            f"{name} has unknown settings {unknown}; {cls.__name__} has {_field_names(cls)}"
        )
    return cls(**fields)


#: The keyword each method's whole options object may also be given as.
_OBJECT_KEYWORDS = {PaperParams: "paper", PaperFeatureParams: "paper", RobustParams: "robust"}
#: Every option any method has: a keyword among them that the chosen method lacks is refused
#: as not applying to it; any other is unknown.
_KNOWN = {
    *_field_names(PaperFeatureParams),
    *_field_names(RobustParams),
    *_OBJECT_KEYWORDS.values(),
    "params",
}


def resolve_params(cls, variant: str, options: Mapping[str, object]):
    """The options of one call, as ``cls`` (:class:`PaperParams`, :class:`PaperFeatureParams`
    or :class:`RobustParams`), the method ``variant`` names.

    ``options`` are the call's keywords (``None`` is "not given"): fields of ``cls``, and its
    whole options object as ``params=`` or by the method's name (``robust=``, ``paper=``;
    an instance or a mapping of its fields). A field keyword replaces the object's field where
    the object leaves it at its default, and contradicts it otherwise.

    Raises:
        ParameterError: a bad value; an option of another method (named, with the variant);
            an unknown option; a keyword contradicting the options object.
    """
    given = {name: value for name, value in options.items() if value is not None}
    unknown = sorted(set(given) - _KNOWN)
    if unknown:
        raise ParameterError(
            f"unknown option{'s' if len(unknown) > 1 else ''} "
            f"{', '.join(map(repr, unknown))}; variant={variant!r} takes {_field_names(cls)}"
        )
    own = _OBJECT_KEYWORDS[cls]
    accepted = {*_field_names(cls), own, "params"}
    refuse_unused(variant, {name: value for name, value in given.items() if name not in accepted})
    objects = [name for name in ("params", own) if name in given]
    if len(objects) > 1:
        raise ParameterError(f"give {own}= or params=, not both")
    base = _as_params(cls, given[objects[0]], objects[0]) if objects else cls()
    fields = {name: value for name, value in given.items() if name in _field_names(cls)}
    if not fields:
        return base
    default = cls()
    for name, value in fields.items():
        ours = getattr(base, name)
        if ours != getattr(default, name) and getattr(cls(**{name: value}), name) != ours:
            raise ParameterError(
                f"{name}={value!r} contradicts {objects[0]}'s {name}={ours!r}: give it once"
            )
    return dataclasses.replace(base, **fields)
