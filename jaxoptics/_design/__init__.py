"""Coating design: targets and the merit function (`_targets`), the design as a padded stack of
layers whose materials are indices into a list (`_layers`), batched least-squares refinement of
many starts (`_refine`), needle synthesis (`_needle`), Monte-Carlo yield, per-layer sensitivity
and robust design under thickness errors (`_errors`), the public `design` with its result
`Design` (`_design`), the TOML design file and the designed sample written back (`_file`), and
the figure of a design (`_plot`).

May import: `_core`, `_runtime`, `_films`, `_io`.
"""
