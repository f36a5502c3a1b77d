"""The narrow-phase methods: one registry that ``zoo.collide``, :class:`zoo.CoherentCollider` and ``zoo.sim`` read.

Each entry says what the method needs of an SDF, its default iterations, and what a simulation uses instead for
an SDF the method cannot take (an analytic SDF has no detector). A new method is an entry here and its solver in
``zoo.collision``'s narrow phase.
"""

from __future__ import annotations

from dataclasses import dataclass

from .errors import InputError
from .validation import int_at_least


@dataclass(frozen=True)
class NarrowPhase:
    """One method of finding each candidate triangle's minimum of the SDF.

    Attributes:
        name: the ``method=`` string.
        description: one line for listings and errors.
        default_iters: iterations when ``iters`` is not given; None for a one-pass method (``iters`` refused).
        needs_detector: the SDF must have ``detect(triangles)`` (a model's shape, ``zoo.load(NAME).shape(...)``).
        fallback: the method ``zoo.sim`` uses for an SDF this one cannot take (None: it takes any SDF).
    """

    name: str
    description: str
    default_iters: int | None
    needs_detector: bool = False
    fallback: str | None = None

    def supports(self, sdf) -> bool:
        return not self.needs_detector or callable(getattr(sdf, "detect", None))


NARROW_PHASES: dict[str, NarrowPhase] = {m.name: m for m in (
    NarrowPhase("fw", "Frank-Wolfe on the SDF (the paper's baseline)", 10),
    NarrowPhase("pgd", "projected gradient descent on the SDF", 32),
    NarrowPhase("voxel-fw", "Frank-Wolfe on a voxel grid of the SDF", 10),
    NarrowPhase("amortized", "the model's detector: the vertex test, one forward pass, the line-search polish", None,
                needs_detector=True, fallback="fw"),
)}


def narrow_phase(name) -> NarrowPhase:
    """The registry's entry for ``name``; an unknown name is an InputError that lists the methods."""
    if name not in NARROW_PHASES:
        raise InputError(f"unknown method {name!r}; use one of {', '.join(repr(m) for m in NARROW_PHASES)}")
    return NARROW_PHASES[name]


def iterations(name: str, iters) -> int | None:
    """The iterations method ``name`` runs: ``iters`` checked, or its default (None for a one-pass method)."""
    method = narrow_phase(name)
    if method.default_iters is None:
        if iters is not None:
            raise InputError(f'iters has no meaning for method="{name}" (one pass); use refine=N for Frank-Wolfe steps after it')
        return None
    return method.default_iters if iters is None else int_at_least(iters, "iters", minimum=1)


def check_supports(name: str, sdf) -> NarrowPhase:
    """The entry for ``name``, after checking that it can take ``sdf`` (an InputError that says what to pass)."""
    method = narrow_phase(name)
    if not method.supports(sdf):
        raise InputError(
            f'method="{name}" needs a shape from a model with a detector: zoo.load(NAME).shape(...); '
            f"{type(sdf).__name__} has no detect(triangles)"
        )
    return method


def method_for(name: str, sdf) -> str:
    """The method a simulation uses for ``sdf`` when asked for ``name``: ``name``, or its fallback where it cannot
    take that SDF."""
    method = narrow_phase(name)
    return name if method.supports(sdf) or method.fallback is None else method.fallback
