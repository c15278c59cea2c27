"""Tools that measure jaxoptics; not imported by ``import jaxoptics``.

- `jaxoptics.tools.bench`: ``python -m jaxoptics bench``, speed (and error) side by side with
  peers on this machine; `bench_stack` is its thin-film section.
- `jaxoptics.tools.stress`: ``python -m jaxoptics stress``, the numerical stress test of every
  kernel; `stress_stack` is its thin-film section.
- `jaxoptics.tools.mpref`: the high-precision mpmath references (the stress test's oracle, and
  the test suite's).

Their extra dependencies (mpmath, tqdm, scipy, tmm) come with ``pip install 'jaxoptics[tools]'``.
"""
