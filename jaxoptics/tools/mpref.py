"""Reference values: 50-digit mpmath transcriptions of the textbook formulas.

Used by the stress test (`python -m jaxoptics stress`) and, as the oracle, by the test suite.
Nothing here calls the kernels: it is an independent transcription. The formulas are the plain ones of Hecht / de Greve (with
`cos_t = sqrt(1 - (eta1/eta2)^2 sin^2)`), which are exact at 50 digits for inputs that are
binary floating-point numbers.
"""

from __future__ import annotations

import functools

import mpmath as mp
import numpy as np

# The references' working precision. Each function below computes at least at it whatever
# precision the caller's mpmath context holds (a caller at 20 digits would otherwise get a reference
# good to far less than float64 near a cancellation: b - a = 1e-9 keeps 11 of 20 digits), and at
# the caller's where that is higher (`mp.diff` raises the precision to difference the function at
# points closer than 50 digits resolve). Importing this module also sets it as mpmath's global
# precision, for the callers' own mpmath arithmetic on the results.
DIGITS = 50
mp.mp.dps = DIGITS


def _at_digits(f):
    """`f` evaluated at `DIGITS` decimal digits, or at the caller's precision where higher."""

    @functools.wraps(f)
    def wrapped(*args, **kwargs):
        with mp.workdps(max(mp.mp.dps, DIGITS)):
            return f(*args, **kwargs)

    return wrapped


def mpf(x):
    return mp.mpf(float(x))


def mpc(x):
    x = complex(x)
    return mp.mpc(x.real, x.imag)


@_at_digits
def fresnel_ref(c, eta1, eta2):
    """Dict of r_s, r_p, t_s, t_p (mpc) and R_s, R_p, T_s, T_p (mpf) at one point."""
    c = abs(c)
    eta2 = mp.mpmathify(eta2)
    # eta2^2 - eta1^2 sin^2 as (eta2^2 - eta1^2) + (eta1 c)^2: at 50 digits `1 - c^2` would round
    # c^2 away for c below 1e-25 (subnormal cosines); this sum is exact whenever the first term is 0
    # and otherwise loses only terms 1e-70 times smaller than it.
    kt = mp.sqrt((eta2**2 - eta1**2) + (eta1 * c) ** 2)
    if mp.im(kt) < 0 or (mp.im(kt) == 0 and mp.re(kt) < 0):
        kt = -kt
    ki = eta1 * c
    if ki + kt == 0:  # grazing with eta1 == eta2: no interface
        z, o = mp.mpc(0), mp.mpc(1)
        return dict(r_s=z, r_p=z, t_s=o, t_p=o, R_s=mp.mpf(0), R_p=mp.mpf(0), T_s=mp.mpf(1), T_p=mp.mpf(1))
    cos_t = kt / eta2
    r_s = (eta1 * c - eta2 * cos_t) / (eta1 * c + eta2 * cos_t)
    r_p = (eta2 * c - eta1 * cos_t) / (eta2 * c + eta1 * cos_t)
    t_s = 2 * eta1 * c / (eta1 * c + eta2 * cos_t)
    t_p = 2 * eta1 * c / (eta2 * c + eta1 * cos_t)
    if ki == 0:
        T_s = T_p = mp.mpf(0)
    else:
        T_s = abs(t_s) ** 2 * mp.re(eta2 * cos_t) / ki
        T_p = abs(t_p) ** 2 * mp.re(eta2 * mp.conj(cos_t)) / ki
    return dict(r_s=r_s, r_p=r_p, t_s=t_s, t_p=t_p, R_s=abs(r_s) ** 2, R_p=abs(r_p) ** 2, T_s=T_s, T_p=T_p)


@_at_digits
def refract_ref(i, n, eta1, eta2):
    """de Greve's refraction in mpmath; i, n sequences of 3 mpf, normalized here (as `refract`
    does: only directions matter). Returns (t, tir)."""
    ni = mp.sqrt(sum(a * a for a in i))
    nn = mp.sqrt(sum(a * a for a in n))
    i = [a / ni for a in i]
    n = [a / nn for a in n]
    d = sum(a * b for a, b in zip(i, n))
    nf = [-x for x in n] if d > 0 else list(n)
    c = abs(d)
    r = eta1 / eta2
    k = 1 - r * r * (1 - c * c)
    if k < 0:
        return [a + 2 * c * b for a, b in zip(i, nf)], True
    ct = mp.sqrt(k)
    return [r * a + (r * c - ct) * b for a, b in zip(i, nf)], False


def spacing(x, dtype):
    return float(np.spacing(np.abs(np.asarray(x, dtype))))


@_at_digits
def fresnel_specials(args, j, lo, hi):
    """Points inside [lo, hi] of input j where the Fresnel functions have a cusp or an interior
    extremum: the critical angle and Brewster's angle. Near the critical angle with a large index
    contrast, r_p swings from +1 through 0 to about -1 within a few ulps, so the sup over the
    interval is not reached at its ends."""
    c, e1, e2 = (mpf(a) for a in args)
    pts = []
    # the critical angle (a cusp) and Brewster's angle (the zero of r_p, a minimum of R_p); for a
    # large index contrast the two lie within an ulp of each other
    if j == 0:
        if e1 > e2:
            pts.append(mp.sqrt(e1**2 - e2**2) / e1)
        pts.append(e1 / mp.sqrt(e1**2 + e2**2))
    elif j == 1 and 0 < c < 1:
        pts += [e2 / mp.sqrt(1 - c * c), e2 * c / mp.sqrt(1 - c * c)]
    elif j == 2:
        pts.append(e1 * mp.sqrt(1 - c * c))
        if c > 0:
            pts.append(e1 * mp.sqrt(1 - c * c) / c)
    return [p for p in pts if mp.im(p) == 0 and lo <= mp.re(p) <= hi]


@_at_digits
def backward_bound(f, args, dtype, ulps=2, specials=None, nonneg=()):
    """Sum over inputs of the largest change of f when that input moves by up to +-ulps ulps.

    `f` maps mp numbers to an mp number (or a list of them, compared by max-abs; complex values
    by modulus). This is the error a backward-stable algorithm may make: what rounding the inputs
    by `ulps` ulps causes. The sup over each interval is taken at its ends and at the points
    `specials(args, j, lo, hi)` returns (cusps inside the interval). Inputs listed in `nonneg`
    (indices, the imaginary part of an index) are not moved below zero.
    """

    def dist(a, b):
        if isinstance(a, (list, tuple)):
            return max(abs(x - y) for x, y in zip(a, b))
        return abs(a - b)

    base = f(*[mpf(a) for a in args])
    total = mp.mpf(0)
    tiny = float(np.finfo(dtype).tiny)
    for j, a in enumerate(args):
        h = mp.mpf(ulps * spacing(a, dtype))
        worst = mp.mpf(0)
        candidates = [mpf(a) + h, mpf(a) - h]
        if specials is not None:
            candidates += specials(args, j, mpf(a) - h, mpf(a) + h)
        if 0 < abs(a) < tiny:
            # XLA (CPU and GPU) runs with denormals-are-zero: a subnormal input acts as 0.
            candidates.append(mp.mpf(0))
        for value in candidates:
            moved = [mpf(x) for x in args]
            moved[j] = value
            if j in nonneg and moved[j] < 0:
                continue
            worst = max(worst, dist(f(*moved), base))
        total += worst
    return base, total


_NAMES = {
    "fresnel": lambda d: (d["R_s"] + d["R_p"]) / 2,
    "fresnel_sp.R_s": lambda d: d["R_s"],
    "fresnel_sp.R_p": lambda d: d["R_p"],
    "fresnel_rt.T": lambda d: (d["T_s"] + d["T_p"]) / 2,
    "fresnel_amplitudes.r_s": lambda d: d["r_s"],
    "fresnel_amplitudes.r_p": lambda d: d["r_p"],
}


@_at_digits
def _schlick(c, a, b):
    r0 = ((a - b) / (a + b)) ** 2
    return r0 + (1 - r0) * (1 - abs(c)) ** 5


@_at_digits
def _schlick_tir(c, a, b):
    c = abs(c)
    if a > b:
        k = (b**2 - a**2) + (a * c) ** 2
        if k < 0:
            return mp.mpf(1)
        c = mp.sqrt(k) / b
    return _schlick(c, a, b)


@_at_digits
def _fresnel_complex(c, a, b):
    """The unpolarized reflectance at the complex index `b (1 + 0.1 i)`."""
    return _NAMES["fresnel"](fresnel_ref(c, a, b * mp.mpc(1, 0.1)))


def scalar_ref(name):
    """The mpmath function (cos_i, eta1, eta2) -> value for a named scalar kernel of the stress test."""
    if name in _NAMES:
        pick = _NAMES[name]
        return lambda c, a, b: pick(fresnel_ref(c, a, b))
    if name == "schlick":
        return _schlick
    if name == "schlick_tir":
        return _schlick_tir
    if name.startswith("fresnel, complex"):
        return _fresnel_complex
    raise KeyError(name)


def bound(name, c, a, b, dtype):
    """(reference, backward bound) at one point, as in `backward_bound`."""
    return backward_bound(scalar_ref(name), (c, a, b), dtype, specials=fresnel_specials, nonneg=(1, 2))


def stack_ref(pol, n, d, wl, theta, dps=40, exact=False):
    """A multilayer by plain characteristic matrices at `dps` digits (no scaling: mpmath's exponent
    range has no overflow). `n` the L indices, `d` the L-2 inner thicknesses, `wl` the vacuum
    wavelength, `theta` the angle of incidence in medium 0 (a float or an mpf). Returns
    (r, t, R, T) in tmm's conventions, as Python numbers, or as mpmath numbers with `exact` (for
    `mp.diff`). Independent of `jaxoptics.stack` (no shared code)."""
    with mp.workdps(dps):
        n = [mp.mpc(x) for x in n]
        s2 = (n[0] * mp.sin(theta if isinstance(theta, mp.mpf) else mp.mpf(theta))) ** 2
        kz = []
        for x in n:
            k = mp.sqrt(x * x - s2)
            kz.append(-k if mp.im(k) < 0 or (mp.im(k) == 0 and mp.re(k) < 0) else k)
        eta = [k if pol == "s" else x * x / k for k, x in zip(kz, n)]
        M = mp.eye(2)
        for j in range(1, len(n) - 1):
            dl = 2 * mp.pi * mp.mpf(d[j - 1]) / mp.mpf(wl) * kz[j]  # mpf() keeps an mpf as it is
            M = M * mp.matrix([[mp.cos(dl), -1j * mp.sin(dl) / eta[j]], [-1j * eta[j] * mp.sin(dl), mp.cos(dl)]])
        v = M * mp.matrix([[1], [eta[-1]]])
        B, C = v[0], v[1]
        r = (eta[0] * B - C) / (eta[0] * B + C)
        if pol == "p":
            r = -r  # tmm's sign of r_p (r_p = -r_s at normal incidence)
        Ex = 2 * eta[0] / (eta[0] * B + C)  # exit tangential E per unit incident tangential E
        if pol == "s":
            t = Ex
        else:  # whole in-plane field: E_p = E_x n / k_z on both sides
            t = Ex * (n[-1] / kz[-1]) / (n[0] / kz[0])
        R = abs(r) ** 2
        T = mp.re(Ex * mp.conj(Ex * eta[-1])) / mp.re(eta[0])
        if exact:
            return r, t, R, T
        return complex(r), complex(t), float(R), float(T)
