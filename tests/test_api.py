"""API conventions: names, keyword-only options, composition with JAX transforms, dtype, shapes."""

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxoptics as jo

PUBLIC_KERNELS = ["reflect", "refract", "fresnel", "fresnel_sp", "fresnel_rt", "fresnel_amplitudes",
                  "schlick", "schlick_tir", "critical_angle", "brewster_angle"]


def test_public_names():
    for name in PUBLIC_KERNELS + ["FresnelAmplitudes", "Refraction"]:
        assert hasattr(jo, name), name
    for name in jo.__all__:
        obj = getattr(jo, name)
        if callable(obj) and not name.startswith("_"):
            assert obj.__doc__, f"{name} has no docstring"


def test_optional_arguments_are_keyword_only():
    """Every parameter with a default must be keyword-only (dm-pix's api_test rule)."""
    for name in jo.__all__:
        obj = getattr(jo, name)
        if not inspect.isfunction(obj) or name.startswith("_"):
            continue
        for p in inspect.signature(obj).parameters.values():
            if p.default is not inspect.Parameter.empty:
                assert p.kind == inspect.Parameter.KEYWORD_ONLY, f"{name}({p.name}=...) can be passed positionally"


def test_public_functions_are_annotated():
    """Every parameter of a public function has a type (arrays with jaxtyping shapes), as has its
    return value."""
    for name in jo.__all__:
        obj = getattr(jo, name)
        if not inspect.isfunction(obj):
            continue
        sig = inspect.signature(obj)
        for p in sig.parameters.values():
            if p.kind is not p.VAR_KEYWORD:
                assert p.annotation is not p.empty, f"{name}({p.name}) has no annotation"
        assert sig.return_annotation is not sig.empty, f"{name} has no return annotation"


def test_kernel_docstrings_state_conventions_and_edge_cases():
    for name in PUBLIC_KERNELS:
        doc = getattr(jo, name).__doc__
        assert "Edge cases" in doc, name


def _ray_batch(dtype, shape=(7,)):
    rng = np.random.default_rng(0)
    n = rng.normal(size=shape + (3,))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    i = rng.normal(size=shape + (3,))
    i /= np.linalg.norm(i, axis=-1, keepdims=True)
    return i.astype(dtype), n.astype(dtype)


KERNEL_CALLS = {
    "reflect": lambda i, n, c, a, b: jo.reflect(i, n),
    "refract": lambda i, n, c, a, b: jo.refract(i, n, a, b),
    "refract_bec": lambda i, n, c, a, b: jo.refract(i, n, a, b, method="bec"),
    "refract_oliveira": lambda i, n, c, a, b: jo.refract(i, n, a, b, method="oliveira", oliveira_c=0.9),
    "refract_heckbert": lambda i, n, c, a, b: jo.refract(i, n, a, b, method="heckbert"),
    "fresnel": lambda i, n, c, a, b: jo.fresnel(c, a, b),
    "fresnel_sp": lambda i, n, c, a, b: jo.fresnel_sp(c, a, b),
    "fresnel_rt": lambda i, n, c, a, b: jo.fresnel_rt(c, a, b),
    "fresnel_amplitudes": lambda i, n, c, a, b: jo.fresnel_amplitudes(c, a, b),
    "fresnel_complex": lambda i, n, c, a, b: jo.fresnel(c, a, jax.lax.complex(b, 0.5 * b)),
    "schlick": lambda i, n, c, a, b: jo.schlick(c, a, b),
    "schlick_tir": lambda i, n, c, a, b: jo.schlick_tir(c, a, b),
    "critical_angle": lambda i, n, c, a, b: jo.critical_angle(a, b),
    "brewster_angle": lambda i, n, c, a, b: jo.brewster_angle(a, b),
}


def _inputs(dtype):
    i, n = _ray_batch(dtype)
    c = np.abs(np.sum(i * n, -1)).astype(dtype)
    a = np.linspace(1.0, 2.0, 7).astype(dtype)
    b = np.linspace(1.6, 1.1, 7).astype(dtype)
    return tuple(jnp.asarray(x) for x in (i, n, c, a, b))


def _real_dtype(x):
    return jnp.finfo(x.dtype).dtype if jnp.iscomplexobj(x) else x.dtype


def test_an_eager_kernel_call_is_one_compiled_program_and_a_traced_one_is_inlined():
    """Called eagerly, each kernel runs as one compiled program: its first call at a new shape
    compiles exactly one program (not each of its operations), a second call at that shape
    compiles nothing, and inside a caller's trace it is inlined (no nested call in the jaxpr).
    (`scene_interface` checks the films' values first, then runs `_scene_program`.) Python ints
    and lists are taken as before: `eta1=1` as a weakly typed float, a list as an array; a bool
    is still refused."""
    rng = np.random.default_rng(8)
    N = 11  # a shape no other test uses, so that nothing is compiled already
    i = rng.normal(size=(N, 3))
    i /= np.linalg.norm(i, axis=-1, keepdims=True)
    n = np.tile([0.0, 0.0, 1.0], (N, 1))
    c, a, b = np.abs(i[:, 2]), rng.uniform(1, 2, N), rng.uniform(1, 2, N)
    calls = {"reflect": lambda s: jo.reflect(i * s, n), "refract": lambda s: jo.refract(i * s, n, a, b),
             "refract[bec]": lambda s: jo.refract(i * s, n, a, b, method="bec"),
             "interface": lambda s: jo.interface(i * s, n, a, b), "critical_angle": lambda s: jo.critical_angle(a * s, b),
             "brewster_angle": lambda s: jo.brewster_angle(a * s, b),
             "_scene_program": lambda s: jo.scene_interface(i * s, n, np.arange(N) % 2, a, b,
                                                            scene=jo.SceneSpec(kinds=("dielectric", "mirror")))}
    for name in ("fresnel", "fresnel_sp", "fresnel_rt", "fresnel_amplitudes", "schlick", "schlick_tir"):
        calls[name] = lambda s, f=getattr(jo, name): f(c * s, a, b)
    compiles = []
    listener = lambda event, duration, **kw: compiles.append(event) if event.endswith("backend_compile_duration") else None
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        for name, call in calls.items():
            del compiles[:]
            jax.block_until_ready(call(1.0))
            assert len(compiles) == 1, (name, len(compiles))
            del compiles[:]
            jax.block_until_ready(call(0.999))
            assert compiles == [], name
            eqns = jax.make_jaxpr(call)(1.0).jaxpr.eqns
            nested = {str(e.params.get("name")) for e in eqns if e.primitive.name in ("pjit", "jit")}
            assert name.split("[")[0] not in nested, (name, nested)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert float(jo.fresnel(0.5, 1, 2)) == float(jo.fresnel(0.5, 1.0, 2.0))
    np.testing.assert_array_equal(np.asarray(jo.reflect([0.6, 0.0, -0.8], [0.0, 0.0, 1.0])),
                                  np.asarray(jo.reflect(np.array([0.6, 0.0, -0.8]), np.array([0.0, 0.0, 1.0]))))
    with pytest.raises(ValueError, match="boolean"):
        jo.fresnel(True, 1.0, 1.5)
    # a specification with a list where a tuple is documented works as it did before the kernels
    # were compiled programs (static arguments must be hashable)
    listed = jo.interface(i[0], n[0], 1.0, 1.5, spec=jo.InterfaceSpec(outputs=["t", "R"]))
    tupled = jo.interface(i[0], n[0], 1.0, 1.5, spec=jo.InterfaceSpec(outputs=("t", "R")))
    np.testing.assert_array_equal(np.asarray(listed.R), np.asarray(tupled.R))
    np.testing.assert_array_equal(np.asarray(listed.t), np.asarray(tupled.t))


@pytest.mark.slow
@pytest.mark.parametrize("name", list(KERNEL_CALLS))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_jit_vmap_match_eager_and_keep_dtype(name, dtype):
    f = KERNEL_CALLS[name]
    args = _inputs(dtype)
    eager = f(*args)
    jitted = jax.jit(f)(*args)
    mapped = jax.vmap(f)(*args)
    for e, j, m in zip(jax.tree_util.tree_leaves(eager), jax.tree_util.tree_leaves(jitted), jax.tree_util.tree_leaves(mapped)):
        if e.dtype != bool:
            assert _real_dtype(e) == dtype, (name, e.dtype)
        np.testing.assert_allclose(np.asarray(j), np.asarray(e), rtol=4 * np.finfo(dtype).eps, atol=4 * np.finfo(dtype).eps)
        np.testing.assert_allclose(np.asarray(m), np.asarray(e), rtol=4 * np.finfo(dtype).eps, atol=4 * np.finfo(dtype).eps)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(KERNEL_CALLS))
def test_grad_jvp_vjp_compose(name):
    f = KERNEL_CALLS[name]
    args = _inputs(np.float64)

    def scalar(*a):
        # distinct weights per output: with equal ones, fresnel_rt's R + T = 1 would make the
        # derivative vanish identically and leave only rounding to compare
        leaves = [x for x in jax.tree_util.tree_leaves(f(*a)) if x.dtype != bool]
        return sum((k + 1) * (jnp.sum(jnp.abs(x) ** 2) if jnp.iscomplexobj(x) else jnp.sum(x)) for k, x in enumerate(leaves))

    g = jax.grad(scalar, argnums=(0, 1, 2, 3, 4))(*args)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in g)
    tangents = tuple(jnp.ones_like(x) for x in args)
    _, jv = jax.jvp(scalar, args, tangents)
    _, pull = jax.vjp(scalar, *args)
    vj = pull(jnp.float64(1.0))
    # <grad, v> from reverse mode equals the forward-mode directional derivative
    np.testing.assert_allclose(float(jv), float(sum(jnp.sum(a) for a in vj)), rtol=1e-10)


@pytest.mark.slow
def test_broadcasting_over_leading_axes():
    i, n = _ray_batch(np.float64, shape=(4, 5))
    e2 = jnp.linspace(1.1, 1.9, 5)  # broadcasts against the last batch axis
    t, tir = jo.refract(i, n[0, 0], 1.0, e2)
    assert t.shape == (4, 5, 3) and tir.shape == (4, 5)
    for a in range(4):
        for b in range(5):
            tt, _ = jo.refract(i[a, b], n[0, 0], 1.0, e2[b])
            np.testing.assert_array_equal(np.asarray(tt), np.asarray(t[a, b]))
    R = jo.fresnel(jnp.linspace(0, 1, 6)[:, None], 1.0, jnp.array([1.2, 1.5]))
    assert R.shape == (6, 2)


def test_results_are_named_and_unpack():
    t, tir = jo.refract(jnp.array([0.6, 0.0, -0.8]), jnp.array([0.0, 0.0, 1.0]), 1.0, 1.5)
    res = jo.refract(jnp.array([0.6, 0.0, -0.8]), jnp.array([0.0, 0.0, 1.0]), 1.0, 1.5)
    assert isinstance(res, jo.Refraction) and res.t is not None and res.tir.dtype == bool
    a = jo.fresnel_amplitudes(0.5, 1.0, 1.5)
    r_s, r_p, t_s, t_p = a
    assert isinstance(a, jo.FresnelAmplitudes)
    np.testing.assert_allclose(float(a.R), float(jo.fresnel(0.5, 1.0, 1.5)), rtol=1e-14)
    R_s, R_p = jo.fresnel_sp(0.5, 1.0, 1.5)
    np.testing.assert_allclose(float(a.R_s), float(R_s), rtol=1e-14)
    np.testing.assert_allclose(float(a.R_p), float(R_p), rtol=1e-14)


@pytest.mark.slow
def test_kernel_results_index_like_tuples():
    """The kernels' results are sequences of their fields in field order, as the tuples they
    unpack as: indexing (negative too), slicing, len, and jnp.stack / np.asarray over them."""
    res = jo.refract(jnp.array([0.6, 0.0, -0.8]), jnp.array([0.0, 0.0, 1.0]), 1.0, 1.5)
    assert len(res) == 2 and res[0] is res.t and res[1] is res.tir and res[-1] is res.tir
    assert res[:1] == (res.t,) and tuple(res) == (res.t, res.tir)
    with pytest.raises(IndexError):
        res[2]
    e = jo.ellipsometry(jnp.array([1.0, 1.46, 3.9]), jnp.array([100.0]), 600.0, 0.8)
    np.testing.assert_array_equal(jnp.stack(e), [e.psi, e.delta])
    np.testing.assert_array_equal(np.asarray(e), [e.psi, e.delta])
    s = jo.stack(jnp.array([1.0, 1.46, 3.9]), jnp.array([100.0]), 600.0, 0.8)
    assert len(s) == 11 and s[0] is s.R_s and s[-1] is s.rp_rs and s[6:8] == (s.r_s, s.r_p)
    a = jo.fresnel_amplitudes(0.5, 1.0, 1.5)
    assert [x is y for x, y in zip(a[::-1], (a.t_p, a.t_s, a.r_p, a.r_s))] == [True] * 4
    for name in ("Interaction", "Hit"):
        assert issubclass(getattr(jo, name), jo.Refraction.__mro__[1]), name  # the same tuple-like base


RESULT_TYPES = ["Refraction", "FresnelAmplitudes", "Interaction", "Hit", "StackResult", "Ellipsometry",
                "FitResult", "DispersionFit", "StackFit"]


@pytest.mark.slow
def test_one_kind_of_result_container():
    """Every result type of the API is the same kind of container: a frozen dataclass registered
    as a JAX pytree, with static fields out of its leaves; `dataclasses.replace` works on it and
    `jit` returns it whole."""
    import dataclasses

    for name in RESULT_TYPES:
        cls = getattr(jo, name)
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen, name
        assert not issubclass(cls, tuple), f"{name} is a tuple"
        assert name in jo.__all__, name
    res = jax.jit(lambda c: jo.stack(jnp.array([1.0, 1.46, 3.9]), jnp.array([100.0]), 600.0, c))(0.8)
    assert isinstance(res, jo.StackResult) and res.r_s.dtype == jnp.complex128
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.R_s = 0.0
    swapped = dataclasses.replace(res, R_s=res.R_p)
    np.testing.assert_array_equal(swapped.R_s, res.R_p)
    # static fields are structure, not leaves: a fit returns from jit with its names
    leaves, tree = jax.tree.flatten(jo.DispersionFit("cauchy", 2, *[jnp.zeros(2)] * 9))
    assert len(leaves) == 9 and jax.tree.unflatten(tree, leaves).model == "cauchy"
    # kernels' results unpack in field order, like `t, tir = refract(...)`
    psi, delta = jo.ellipsometry(jnp.array([1.0, 1.46, 3.9]), jnp.array([100.0]), 600.0, 0.8)
    e = jo.ellipsometry(jnp.array([1.0, 1.46, 3.9]), jnp.array([100.0]), 600.0, 0.8)
    assert (psi, delta) == (e.psi, e.delta)


@pytest.mark.slow
def test_float32_stays_float32_with_python_scalars():
    c = jnp.linspace(0, 1, 5, dtype=jnp.float32)
    assert jo.fresnel(c, 1.0, 1.5).dtype == jnp.float32
    assert jo.fresnel_amplitudes(c, 1, 1.5).r_s.dtype == jnp.complex64
    assert jo.fresnel(c, 1.0, 0.2 + 3j).dtype == jnp.float32
    assert jo.refract(jnp.ones((2, 3), jnp.float32), jnp.ones(3, jnp.float32), 1.0, 1.5).t.dtype == jnp.float32
