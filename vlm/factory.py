"""Backends from one-line specs, as configs and CLIs write them.

=====================================  ===================================================
spec                                   backend
=====================================  ===================================================
``sim:<preset>``                       :class:`vlm.sim.SimulatedVlm` (preset from ``vlm.sim.PRESETS``)
``http:<url>[#model]``                 :class:`vlm.backend_http.HttpBackend`; ``<url>`` may be
                                       ``http://host:port[/v1]`` or ``host:port``; plain
                                       ``http://...`` / ``https://...`` specs work too. Without
                                       ``#model`` the server's first ``/v1/models`` id is used.
``transformers:<path-or-dir>``         :class:`vlm.backend_transformers.TransformersBackend`
=====================================  ===================================================

Keyword options are passed to the backend's config dataclass (e.g. ``timeout_s=2.0`` for
HTTP, ``device="cuda"`` for transformers); an unknown option is a ValueError naming the valid
ones. Heavy modules (torch, transformers, the simulator) are imported only for the kind asked.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from vlm.types import VlmBackend

__all__ = ["VALID_SPECS", "make_backend"]

VALID_SPECS = "sim:<preset> | http:<url>[#model] (or http://host:port[/v1][#model]) | transformers:<path-or-dir>"
_HUB_ID = re.compile(r"^[\w.-]+/[\w.-]+$")


def _bad_spec(spec: object, why: str) -> ValueError:
    return ValueError(f"bad VLM backend spec {spec!r}: {why}; valid forms: {VALID_SPECS}")


def _checked_options(config_class, options: dict, fixed: tuple[str, ...]) -> dict:
    allowed = sorted(f.name for f in dataclasses.fields(config_class) if f.name not in fixed)
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ValueError(f"unknown option(s) {unknown} for {config_class.__name__}; valid: {allowed}")
    return options


def make_backend(spec: str, *, seed: int = 0, **options) -> VlmBackend:
    """Build the backend a spec names (see the module docstring).

    Parameters
    ----------
    spec : backend spec string
    seed : seed of the simulated VLM (real backends decode greedily and ignore it)
    options : fields of the backend's config dataclass

    Raises
    ------
    ValueError : the spec or an option is wrong (the message lists the valid forms)
    vlm.types.VlmError : the backend exists but cannot be reached / loaded
    """
    if not isinstance(spec, str) or ":" not in spec:
        raise _bad_spec(spec, "expected <kind>:<argument>")
    kind, _, rest = spec.partition(":")
    kind = kind.strip().lower()
    if kind == "sim":
        return _make_sim(spec, rest.strip(), seed, options)
    if kind in ("http", "https"):
        return _make_http(spec, kind, rest.strip(), options)
    if kind == "transformers":
        return _make_transformers(spec, rest.strip(), options)
    raise _bad_spec(spec, f"unknown kind {kind!r}")


def _make_sim(spec: str, preset: str, seed: int, options: dict) -> VlmBackend:
    if not preset:
        raise _bad_spec(spec, "sim needs a preset name")
    try:
        from vlm.sim import PRESETS, SimulatedVlm
    except ImportError as exc:
        raise ValueError(f"the simulated VLM (vlm.sim) is not available: {exc}") from exc
    if preset not in PRESETS:
        raise _bad_spec(spec, f"unknown simulated-VLM preset {preset!r} (presets: {', '.join(sorted(PRESETS))})")
    try:
        return SimulatedVlm(preset=preset, seed=seed, **options)
    except TypeError as exc:  # an option SimulatedVlm does not take
        raise ValueError(f"bad option for the simulated VLM: {exc}") from exc


def _make_http(spec: str, kind: str, rest: str, options: dict) -> VlmBackend:
    from vlm.backend_http import HttpBackend, HttpBackendConfig

    url, _, model = rest.partition("#")
    if kind == "https" or url.startswith("//"):  # a plain "http://..." / "https://..." spec
        url = f"{kind}:{url}"
    elif "://" in url and not url.startswith(("http://", "https://")):
        raise _bad_spec(spec, "only http and https servers (base_url must be http(s)://host:port)")
    elif not url.startswith(("http://", "https://")):
        url = "http://" + url
    if not url.split("://", 1)[1].strip("/"):
        raise _bad_spec(spec, "http needs a server address")
    feature_source = options.pop("feature_source", None)  # a local vision-feature source (HttpBackend docs)
    _checked_options(HttpBackendConfig, options, ("base_url", "model"))
    try:
        config = HttpBackendConfig(base_url=url, model=model.strip() or "unresolved", **options)
    except ValueError as exc:
        raise _bad_spec(spec, str(exc)) from exc
    backend = HttpBackend(config, feature_source=feature_source)
    if model.strip():
        return backend
    models = backend.list_models(timeout_s=min(config.timeout_s, 5.0))
    if not models:
        raise ValueError(f"{url} serves no models; name one with {spec}#<model>")
    return HttpBackend(dataclasses.replace(config, model=models[0]), feature_source=feature_source)


def _make_transformers(spec: str, path: str, options: dict) -> VlmBackend:
    if not path:
        raise _bad_spec(spec, "transformers needs a checkpoint directory")
    if not Path(path).expanduser().is_dir() and not _HUB_ID.match(path):
        raise _bad_spec(spec, f"no checkpoint directory at {path!r}")
    from vlm.backend_transformers import TransformersBackend, TransformersBackendConfig

    _checked_options(TransformersBackendConfig, options, ("model_path",))
    model_path = str(Path(path).expanduser()) if Path(path).expanduser().is_dir() else path
    return TransformersBackend(TransformersBackendConfig(model_path=model_path, **options))
