"""Method registry: benchmark method name -> factory.

A factory builds a fresh method for one episode::

    factory(vlm_spec: str, seed: int, **options) -> Method

``vlm_spec`` is a :func:`vlm.factory.make_backend` spec (``"sim:nominal"``); ``seed`` is the
episode's seed. ``options`` are plain TOML values from the benchmark config: the shared tables
``planner``, ``esdf`` and ``verifier`` (dicts of config-field overrides, passed to every method)
and the method's own table ``[methods.<name>]``. A factory raises a ValueError naming any
option it does not know.

Methods register with :func:`register` (the OnFly pilot, its ablations and the baselines do so
from their own modules, listed in :data:`PROVIDERS` so the runner and worker processes find
them without importing them by hand).
"""

from __future__ import annotations

import importlib
import logging
from typing import Callable

from onfly.bench.method import Method
from onfly.bench.oracle import make_oracle

__all__ = ["METHODS", "PROVIDERS", "register", "get_factory", "method_names", "make_method", "UnknownMethodError"]

log = logging.getLogger(__name__)

Factory = Callable[..., Method]

#: name -> factory. Edit through :func:`register`.
METHODS: dict[str, Factory] = {"oracle": make_oracle}

#: Modules imported (once) before a name is looked up; each calls :func:`register` at import.
#: A module that is missing or fails to import is logged and skipped.
PROVIDERS: tuple[str, ...] = ("onfly.bench.onfly_method", "onfly.baselines")

_loaded = False


class UnknownMethodError(ValueError):
    """A method name that is not registered (the message lists the valid names)."""


def register(name: str, factory: Factory, *, replace: bool = False) -> None:
    """Register ``factory`` under ``name`` (a second registration needs ``replace=True``)."""
    if not isinstance(name, str) or not name or any(c in name for c in ", \t\n"):
        raise ValueError(f"method name must be a non-empty string without commas or spaces, got {name!r}")
    if not callable(factory):
        raise ValueError(f"factory for {name!r} is not callable: {factory!r}")
    if name in METHODS and METHODS[name] is not factory and not replace:
        raise ValueError(f"method {name!r} is already registered (pass replace=True to override)")
    METHODS[name] = factory


def _load_providers() -> None:
    global _loaded
    if _loaded:
        return
    _loaded = True
    for mod in PROVIDERS:
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                log.warning("method provider %s failed to import: %s", mod, exc)
        except Exception as exc:  # a broken provider must not hide the others
            log.warning("method provider %s failed to import: %r", mod, exc)


def method_names() -> list[str]:
    """Registered method names, sorted."""
    _load_providers()
    return sorted(METHODS)


def get_factory(name: str) -> Factory:
    """The factory of ``name``; UnknownMethodError lists the valid names."""
    _load_providers()
    try:
        return METHODS[name]
    except KeyError:
        raise UnknownMethodError(f"unknown method {name!r}; registered methods: {', '.join(sorted(METHODS))}") from None


def make_method(name: str, vlm_spec: str, seed: int, **options) -> Method:
    """Build a fresh method for one episode."""
    return get_factory(name)(vlm_spec, seed, **options)
