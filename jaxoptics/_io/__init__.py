"""Data files and model files: reflectance curves (`_reflectance`), spectra of layered samples
(`_spectra`: ellipsometry and photometry, from CSV or arrays), and the TOML description of a
sample (`_model_file`).

May import: `_core`, `_films`.
"""
