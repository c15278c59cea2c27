"""The one kind of result container of the public API.

Every result a computation returns (`Refraction`, `FresnelAmplitudes`, `Interaction`, `Hit`,
`StackResult`, `Ellipsometry`, `FitResult`, `DispersionFit`, `StackFit`) is a frozen dataclass
registered as a JAX pytree with `jax.tree_util.register_dataclass`: fields by name,
`dataclasses.replace` and `dataclasses.fields`, methods and properties, static fields (names,
model choices) kept out of the leaves, and the same behaviour under `jit`, `vmap` and the tree
utilities as an `equinox.Module` (which is itself such a dataclass). The kernels' modules do not
import equinox: loading it costs 0.2-0.3 s, more than twice what `import jaxoptics` adds to JAX
itself, which a program calling only the kernels does not need.

The kernels' results (`Unpacks`) also behave as the tuples of their fields in field order, as
`NamedTuple`s do: they unpack (`t, tir = refract(...)`, `psi, delta = ellipsometry(...)`), index
and slice (`refract(...)[0]`, `stack(...)[:2]`), have a length, and stack
(`jnp.stack(ellipsometry(...))`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any, TypeVar, dataclass_transform

import jax

T = TypeVar("T")


def static(**kwargs: Any) -> Any:
    """A field kept out of the pytree's leaves (part of its structure): a name, a model choice."""
    return dataclasses.field(metadata={"static": True}, **kwargs)


@dataclass_transform(frozen_default=True, field_specifiers=(dataclasses.field, static))
def result(cls: type[T]) -> type[T]:
    """Make `cls` a frozen dataclass registered as a JAX pytree; fields made with `static()` are
    metadata. Instances compare by identity (`==` on their arrays would be elementwise)."""
    cls = dataclasses.dataclass(frozen=True, eq=False)(cls)
    fields = dataclasses.fields(cls)  # type: ignore[arg-type]
    data = [f.name for f in fields if not f.metadata.get("static")]
    meta = [f.name for f in fields if f.metadata.get("static")]
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    return cls


class Unpacks:
    """Base of the kernels' results: the tuple of the fields in field order, for unpacking,
    indexing, slicing and `len` (as a `NamedTuple`; the fields keep their names too)."""

    def _astuple(self) -> tuple:
        return tuple(getattr(self, f.name) for f in dataclasses.fields(self))  # type: ignore[arg-type]

    def __iter__(self) -> Iterator[Any]:
        return iter(self._astuple())

    def __len__(self) -> int:
        return len(dataclasses.fields(self))  # type: ignore[arg-type]

    def __getitem__(self, index):
        return self._astuple()[index]
