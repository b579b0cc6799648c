"""ilt: inverse light transport (Seitz, Matsushita & Kutulakos, ICCV 2005)."""

import importlib

__version__ = "0.1.0"


def lazy_face(package: str, submod_attrs: dict[str, list[str]]):
    """A package's face (PEP 562): ``(__getattr__, __dir__, __all__)`` for its
    ``__init__``, which names each public function by the module that defines it and
    imports that module only when the name is first used (``import ilt.transport`` loads
    no numpy). Submodules are reachable as attributes too."""
    where = {name: module for module, names in submod_attrs.items() for name in names}
    names = sorted(where)

    def __getattr__(name: str):
        if name in where:
            return getattr(importlib.import_module(f"{package}.{where[name]}"), name)
        if name in submod_attrs:
            return importlib.import_module(f"{package}.{name}")
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__():
        return names

    return __getattr__, __dir__, names
