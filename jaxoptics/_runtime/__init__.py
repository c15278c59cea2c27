"""Compilation, caching and devices: the fits' compiler options (`_options`), `filter_jit`
(`_compile`), the store of compiled programs kept between processes (`_cache`), malloc's
handling of freed memory (`_memory`), and meshes and batch sharding (`_shard`).

May import: `_core`.
"""
