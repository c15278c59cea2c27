"""Data files and model files: reflectance curves (`_reflectance`); spectra of layered samples
(`_spectra`: the `Spectra` container, from arrays or saved as CSV), read from any supported file by
`_load` (`load_spectra`, format detection): jaxoptics' CSV (`_csv`), ellipsometers' exports
(`_vendors`: Woollam, SpectraRay, Accurion, Horiba, Film Sense), NeXus `NXellipsometry`
(`_nexus`), spectrophotometers' R/T text and JCAMP-DX (`_photometry`), with the conventions of
Delta and of Mueller matrices as options (`_conventions`); tables of optical constants from
other tools (`_nk_file`); and the TOML description of a sample (`_model_file`).

May import: `_core`, `_films`.
"""
