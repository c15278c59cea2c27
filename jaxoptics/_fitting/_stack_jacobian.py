"""The Jacobian of a layered sample's model in its free parameters, by the chain rule through the
stack's inputs with as few passes through the stack as the model allows (`_jacobian_plan`)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._core._numerics import materialize
from .._films._dispersion import Free, parameter_leaves
from .._films._graded import Graded
from .._films._sample import model_quantities
from .._films._stack import stack


def _model_and_jacobian(sample, kinds, wl, ang):
    """`x -> (model, J)`: the quantities `kinds` at the points `(wl, ang)` (nm, radians), flat
    `(Q P,)`, and their Jacobian `(Q P, p)` in the free parameters `x`, by the chain rule through the
    stack's inputs (`_jacobian_plan`). With an `Instrument`, whose conditions the model averages
    over, the Jacobian is the forward-mode derivative of the whole model, one tangent per
    parameter."""
    if sample.instrument is not None:
        q = len(sample.free())
        model = lambda x: sample.with_values([x[i] for i in range(q)]).quantities(kinds, wl, ang, flat=True)

        def model_and_jac_averaged(x):
            basis = jnp.eye(q, dtype=x.dtype)
            return jax.vmap(lambda t: jax.jvp(model, (x,), (t,)), out_axes=(None, 1))(basis)

        return model_and_jac_averaged
    plan = _jacobian_plan(sample)
    p, Q = len(plan.columns), len(kinds)
    inc = sample.incoherent
    cos_ang = jnp.cos(ang)
    inputs = lambda x: sample.with_values([x[i] for i in range(p)]).stack_inputs(wl)
    quantities = lambda n, d: model_quantities(stack(n, d, wl, cos_ang, incoherent=inc), kinds, True)

    def model_and_jac(x):
        basis = jnp.eye(p, dtype=x.dtype)
        (n, d), (dn, dd) = jax.vmap(lambda t: jax.jvp(inputs, (x,), (t,)), out_axes=(None, -1))(basis)
        tn, td = [], []
        for kind, j in plan.directions:
            if kind == "param":
                tn.append(dn[..., j])
                td.append(dd[..., j])
            else:
                tn.append(jnp.zeros_like(n).at[..., j].set(1 if kind == "re" else 1j))
                td.append(jnp.zeros_like(d))
        m, D = jax.vmap(lambda a, b: jax.jvp(quantities, (n, d), (a, b)), out_axes=(None, 1))(jnp.stack(tn), jnp.stack(td))
        # stored once: under `vmap` over the directions, XLA otherwise fuses the stack's last steps
        # into the loop that assembles the columns, where they run one element at a time (4x the
        # cost of the whole Jacobian, measured on a film's R_s)
        D = materialize(D)
        cols = []
        for i in range(p):
            src = plan.columns[i]
            if len(src) == 1:  # the parameter's own direction
                cols.append(D[:, src[0]])
            else:  # d/dx_i = d/dRe(n_j) Re(dn_j/dx_i) + d/dIm(n_j) Im(dn_j/dx_i), point by point
                k_re, k_im = src
                g = jnp.tile(dn[:, plan.medium[i], i], Q)
                col = D[:, k_re] * jnp.real(g)
                cols.append(col if k_im is None else col + D[:, k_im] * jnp.imag(g))
        return m, jnp.stack(cols, axis=1)

    return model_and_jac


class _Plan(NamedTuple):
    directions: tuple  # tangents through the stack: ("param", i), ("re", j) or ("im", j)
    columns: tuple  # per free parameter: (direction,) or (re direction, im direction or None)
    medium: tuple  # per free parameter: the column of the medium it belongs to among the stack's media (None for a thickness)


def _jacobian_plan(sample):
    """How `fit_stack` builds the Jacobian of the model in the free parameters `x`.

    The model is `quantities(stack(n(x), d(x)))`: cheap per-point dispersion formulas `n(x)` of
    the `L` media and the thicknesses `d(x)`, then the stack, which costs nearly all the time. Its
    forward-mode derivative costs about one stack evaluation per tangent, so the tangents through
    the stack are kept few: a medium with more than two free parameters gets two (its index's real
    and imaginary part, at every point at once: each point depends on its own index only), or one
    where its index is real (the incident medium; a model whose `k` is held at zero, such as
    Cauchy's without an Urbach tail), and the derivative in each of its parameters is their
    point-by-point combination with the dispersion formula's derivatives. Every other parameter
    (a thickness, or a medium with one or two) is its own tangent. On the benchmark's film (Cauchy
    A, B, C and the thickness free) that is 2 tangents instead of 4."""
    columns_of = sample._columns()
    slot, counts, real, graded = [], [], [], []
    for j, (_, model) in enumerate(sample._slots()):
        k = sum(isinstance(leaf, Free) for _, leaf in parameter_leaves(model))
        slot += [j] * k
        counts.append(k)
        real.append(j == 0 or model._real())
        graded.append(isinstance(model, Graded))  # its parameters move several media: each its own tangent
    slot += [None] * sum(isinstance(layer.thickness_nm, Free) for layer in sample.layers)
    directions, columns, split = [], [], {}
    for i, j in enumerate(slot):
        if j is not None and counts[j] > 2 and not graded[j]:
            if j not in split:
                split[j] = (len(directions), None if real[j] else len(directions) + 1)
                directions += [("re", columns_of[j])] + ([] if real[j] else [("im", columns_of[j])])
            columns.append(split[j])
        else:
            columns.append((len(directions),))
            directions.append(("param", i))
    medium = tuple(None if j is None else columns_of[j] for j in slot)
    return _Plan(tuple(directions), tuple(columns), medium)
