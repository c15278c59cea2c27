"""Tools that measure jaxoptics; not imported by ``import jaxoptics``. They may import any part of
the package (through its public API where they can); nothing in the package imports them except
the command line (`jaxoptics.__main__`).

- `bench`: ``python -m jaxoptics bench``, speed (and error) side by side with peers on this
  machine; its sections are `bench_kernels`, `bench_fit` (index fits and devices),
  `bench_stack`, `bench_stack_fit` and `bench_latency`.
- `stress`: ``python -m jaxoptics stress``, the numerical stress test of every kernel;
  `stress_stack` is its thin-film section.
- `mpref`: the high-precision mpmath references (the stress test's oracle, and the test suite's).
- `_measure`: what they share (the machine's description, the timing convention, two peers).
- `make_programs`, `make_examples`, `materials_data`: write the package's shipped data (traced
  programs, the bundled examples, the built-in materials).

Their extra dependencies (mpmath, tqdm, scipy, tmm, pyElli) come with
``pip install 'jaxoptics[tools]'``.
"""
