"""What every scene shares: a typed configuration with ``--set key=value`` overrides, and the
standard outputs (summary.json, run.h5, figures).

A scene module defines a ``Config`` dataclass (SI units in the field comments), ``QUICK``
(overrides for a small, fast version used by tests and CI) and ``run(config, out_dir) ->
summary dict``.
"""

from __future__ import annotations

import dataclasses
import json
import platform
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np


def apply_overrides(config: Any, overrides: dict[str, str] | None) -> Any:
    """Return a copy of the dataclass ``config`` with string overrides cast to each field's
    type; unknown keys raise ValueError listing the valid ones."""
    if not overrides:
        return config
    fields = {f.name: f for f in dataclasses.fields(config)}
    changes = {}
    for key, raw in overrides.items():
        if key not in fields:
            raise ValueError(
                f"unknown setting {key!r}; valid settings: {', '.join(sorted(fields))}"
            )
        current = getattr(config, key)
        changes[key] = _cast(raw, current, key)
    return dataclasses.replace(config, **changes)


def _cast(raw: str | Any, current: Any, key: str) -> Any:
    if not isinstance(raw, str):
        return raw
    try:
        if isinstance(current, bool):
            if raw.lower() in ("1", "true", "yes", "on"):
                return True
            if raw.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(raw)
        if isinstance(current, int):
            return int(float(raw)) if float(raw).is_integer() else int(raw)
        if isinstance(current, float):
            return float(raw)
        if isinstance(current, tuple):
            return _cast_tuple(raw, current)
        return raw
    except ValueError as exc:
        raise ValueError(
            f"setting {key}={raw!r} cannot be read as {type(current).__name__}"
        ) from exc


def _cast_tuple(raw: str, current: tuple) -> tuple:
    """``"1e6, 2e6"`` (brackets optional) -> a tuple. A tuple of one element type (every
    tuple setting of the scenes: confinements, pressures, snapshot times) takes any number
    (at least one) of values of that type; a mixed tuple needs one value per element."""
    body = raw.strip().strip("()[]").strip()
    items = [v.strip() for v in body.split(",") if v.strip()] if body else []
    if not items:
        raise ValueError("a list setting needs at least one value")
    kinds = {type(c) for c in current}
    if len(kinds) <= 1:
        kind = kinds.pop() if kinds else (int if all(_is_int(v) for v in items) else float)
        return tuple(_scalar(v, kind) for v in items)
    return tuple(_scalar(v, type(c)) for c, v in zip(current, items, strict=True))


def _is_int(v: str) -> bool:
    try:
        int(v)
    except ValueError:
        return False
    return True


def _scalar(v: str, kind: type) -> Any:
    if kind is int:
        x = float(v)
        if not x.is_integer():
            raise ValueError(v)
        return int(x)
    return kind(v)


def same_scene(a: str, b: str) -> bool:
    """Whether two scene names are the same scene: summaries written before 2026-12-06 name
    the oedometers by their module (``oedometer_cantor``), the CLI by ``oedometer-cantor``."""
    return a.replace("_", "-") == b.replace("_", "-")


def read_config_file(path: Path, scene: str) -> dict[str, Any]:
    """Settings of ``scene`` from a JSON file: a run's ``summary.json`` (its ``config``, so a
    run can be repeated or varied with ``--set``) or a plain object of settings (SI units,
    as ``jaxgran settings SCENE`` lists them). ValueError, naming the file, where it cannot
    be read, is not an object, or is the summary of another scene; unknown setting names are
    refused later by :func:`apply_overrides`."""
    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise ValueError(f"cannot read the configuration file {path}: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path} must hold a JSON object of settings or a run's summary")
    if "config" in data and isinstance(data["config"], dict):
        # summaries written before 2026-12-06 name the oedometers by module (oedometer_cantor)
        stored = str(data.get("scene", scene))
        if not same_scene(stored, scene):
            raise ValueError(f"{path} is the summary of a {stored!r} run, not {scene!r}")
        data = data["config"]
    return data


def unrecorded_settings(path: Path, config: Any, settings: dict[str, Any]) -> dict[str, Any]:
    """Settings of ``config`` (a scene's Config) that the run summary at ``path`` does not
    record, with the values they take now (today's defaults, or ``--quick``'s): settings added
    after that run was made, whose defaults may differ from what the run used (e.g.
    ``oedometer-cantor``'s ``settle_friction``, 0 since 2026-12-06, where runs before it
    settled with the contact friction). Empty for a plain object of settings, which sets only
    what it names by intent."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    if not (isinstance(data, dict) and isinstance(data.get("config"), dict)):
        return {}
    return {
        f.name: getattr(config, f.name)
        for f in dataclasses.fields(config)
        if f.name not in settings
    }


def parse_sets(items: list[str] | None) -> dict[str, str]:
    """``["a=1", "b=x"]`` -> ``{"a": "1", "b": "x"}`` with a clear error for bad items."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def environment() -> dict[str, Any]:
    """Versions and machine facts stored with every run."""
    from .. import __version__

    return {
        "jaxgran_version": __version__,
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "backend": jax.default_backend(),
        "x64": bool(jax.config.jax_enable_x64),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }


def write_outputs(
    out_dir: Path,
    scene: str,
    config: Any,
    result,
    params,
    summary: dict,
    *,
    events: list[dict] | None = None,
    figures: bool = True,
    vtk: bool = False,
) -> dict:
    """Write summary.json, run.h5 and the standard figures; return the summary."""
    from .. import io

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {"scene": scene, "config": dataclasses.asdict(config), **environment()}
    summary = {"scene": scene, **summary, "config": dataclasses.asdict(config), **environment()}
    io.write_run(out_dir / "run.h5", result, params, metadata=meta, events=events)
    io.write_summary(out_dir / "summary.json", summary)
    if figures:
        from .. import plot

        summary["figures"] = [
            str(p) for p in plot.plot_run(io.read_run(out_dir / "run.h5"), out_dir)
        ]
        io.write_summary(out_dir / "summary.json", summary)
    if vtk:
        io.write_vtk(out_dir / "vtk" / "frame", io.read_run(out_dir / "run.h5"))
    return summary


def finished_summary(out_dir: Path, scene: str, config: Any) -> dict | None:
    """The summary.json in ``out_dir`` if a run of ``scene`` with exactly ``config`` finished
    there (so that a resumed batch of long runs skips the done ones), else None.

    The figures' paths are given in ``out_dir``: a summary stores them as they were named
    when the run was made (relative to the directory it was started from), and the folder
    may since have been moved or be read from another working directory."""
    out_dir = Path(out_dir)
    path = out_dir / "summary.json"
    if not path.exists():
        return None
    summary = json.loads(path.read_text())
    want = json.loads(json.dumps(dataclasses.asdict(config), default=float))
    if not same_scene(str(summary.get("scene")), scene) or summary.get("config") != want:
        return None
    if "figures" in summary:
        summary["figures"] = [
            str(out_dir / Path(f).name) if (out_dir / Path(f).name).exists() else f
            for f in summary["figures"]
        ]
    return summary


def dumps(summary: dict) -> str:
    """Compact human-readable summary for the terminal."""
    keep = {k: v for k, v in summary.items() if k not in ("config", "figures")}
    return json.dumps(keep, indent=2, default=float)


def contact_params(cfg: Any, reference_mass: float, **extra):
    """Contact parameters from a scene config with the fields ``normal_stiffness``,
    ``tangential_stiffness``, ``friction``, ``restitution``, ``skin`` and ``thickness``: the
    normal and tangential dashpots give the restitution ``cfg.restitution`` to a pair of
    particles of mass ``reference_mass`` (kg). ``extra`` goes to ``make_params``."""
    from ..contact import damping_from_restitution
    from ..state import make_params

    m_eff = reference_mass / 2
    return make_params(
        normal_stiffness=cfg.normal_stiffness,
        tangential_stiffness=cfg.tangential_stiffness,
        friction=cfg.friction,
        normal_damping=damping_from_restitution(cfg.restitution, cfg.normal_stiffness, m_eff),
        tangential_damping=damping_from_restitution(
            cfg.restitution, cfg.tangential_stiffness, m_eff
        ),
        skin=cfg.skin,
        thickness=cfg.thickness,
        **extra,
    )
