"""The unconstrained ablation: factors of a group taken off the group, into their embedding space.

``relax(group, ["R"])`` replaces the factor ``R`` of a :class:`groups.Product` by
``Euclidean(embedding_dim)``, the vector space its embedding lives in (``R^9`` for SO(3)). The
element layout stays the same (``vec R`` row-major is both SO(3)'s flat element and its
embedding), so the data, the loss and the system's metrics read the relaxed estimates
unchanged. An observer on the relaxed group with the rule ``absolute`` for ``R`` predicts
``vec R`` directly, a plain regression with nothing that keeps it a rotation: the ablation that
shows what the group update of the paper is worth (its distance from SO(3) is reported by the
*system's* group, ``system.group.membership_error``, in the evaluation).

Only factors whose embedding is their flattened element can be relaxed (SO(2), SO(3), R^n):
for SE(3) the embedding ``(vec R, t)`` (12) is not the element (16), and a flat estimate of 12
numbers would not fit the state's layout.
"""

from __future__ import annotations

from collections.abc import Sequence

from groups import Euclidean, LieGroup, Product

__all__ = ["relax"]


def relax(group: LieGroup, names: Sequence[str]) -> LieGroup:
    """``group`` with the factors ``names`` replaced by ``Euclidean(embedding_dim)``.

    The names are ``group.factor_names`` (a non-product group is one factor named ``x``;
    unnamed product factors are ``factor0``, ...). Returns ``group`` itself when ``names`` is
    empty. Raises ``ValueError`` for an unknown factor or one whose embedding is not its
    flattened element.
    """
    names = list(names)
    if not names:
        return group
    factors, have = group.factors, list(group.factor_names)
    unknown = [n for n in names if n not in have]
    if unknown:
        raise ValueError(
            f"relax names factors {unknown} that the group {group!r} does not have; its "
            f"factors: {have}."
        )
    out = []
    for f, name in zip(factors, have):
        if name not in names or isinstance(f, Euclidean):
            out.append(f)
            continue
        if not f.embedding_is_flat:
            raise ValueError(
                f"cannot relax factor {name!r} ({f!r}): its embedding ({f.embedding_dim} numbers) "
                f"is not its flattened element {tuple(f.element_shape)}, so an unconstrained "
                "estimate would not fit the state's layout. Relax SO(2)/SO(3)-like factors, or "
                "use the direct-product form of the system's group."
            )
        out.append(Euclidean(f.embedding_dim))
    if not isinstance(group, Product):
        if tuple(group.element_shape) != tuple(out[0].element_shape):
            raise ValueError(
                f"cannot relax {group!r} itself: its elements {tuple(group.element_shape)} are "
                f"not flat like R^{out[0].embedding_dim}'s; wrap it in a Product (flat elements)."
            )
        return out[0]
    return Product(*out, names=group.names)
