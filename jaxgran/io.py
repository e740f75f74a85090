"""Run files: HDF5 (``run.h5``), VTK for ParaView and ``summary.json``.

This is the only module that touches h5py and VTK files (DESIGN §2, §8). Everything here is
host-side numpy; nothing is traced.

Layout of a run file written by :func:`write_run` (root attrs ``format = "jaxgran-run"``,
``format_version``)::

    /params        one attribute per Params field; non-scalar fields (gravity) as datasets
    /metadata      attrs: scene, jaxgran/jax/h5py versions, dtype, date, steps, wall time,
                   grid, regrows, plus the caller's metadata (dicts/lists as JSON strings,
                   their names listed in the attr ``_json``)
    /series/<name> time series, leading axis = record            (e.g. kinetic_energy [R])
    /frames/<name> frames stacked on a leading frame axis F       (pos [F, P, 2], verts
                   [F, P, V, 2] in the body frame, n_verts/radius/uid [F, P], ...)
    /events        the event log, one entry per field (see :func:`write_run`)
    /final         final particle arrays; /final/walls and /final/bonds for those pytrees

Datasets with more than 1,000 elements are chunked and gzip-compressed; datasets carry a
``units`` attribute where the unit is known (SI).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from .errors import SceneError
from .geometry import spheropolygon_outline

if TYPE_CHECKING:
    from .simulate import RunResult
    from .state import Params, Particles

log = logging.getLogger(__name__)

FORMAT_NAME = "jaxgran-run"
FORMAT_VERSION = 1
_COMPRESS_ABOVE = 1000  # elements

# SI units of the names that appear in series, frames and final arrays.
UNITS: dict[str, str] = {
    "time": "s",
    "kinetic_energy": "J",
    "rotational_energy": "J",
    "mean_speed": "m/s",
    "mean_angular_speed": "rad/s",
    "pos": "m",
    "verts": "m",
    "radius": "m",
    "bound_radius": "m",
    "angle": "rad",
    "vel": "m/s",
    "omega": "rad/s",
    "force": "N",
    "torque": "N m",
    "mass": "kg",
    "inertia": "kg m^2",
    "wall_point": "m",
    "wall_force": "N",
    "point": "m",
    "extent": "m",
    "length": "m",
    "target_stress": "Pa",
    "servo_gain": "m/(s Pa)",
    "max_speed": "m/s",
    "servo_time": "s",
    "servo_integral": "m/s",
    "contact_force": "N",
}

PARAM_UNITS: dict[str, str] = {
    "normal_stiffness": "N/m",
    "tangential_stiffness": "N/m",
    "friction": "1",
    "wall_friction": "1",
    "normal_damping": "1/s",
    "tangential_damping": "1/s",
    "gravity": "m/s^2",
    "dt": "s",
    "skin": "m",
    "thickness": "m",
    "shear_modulus": "Pa",
    "poisson_ratio": "1",
}

# Per-particle frame keys, and the value that pads a particle slot that did not exist yet.
_PARTICLE_PAD = {"active": False, "uid": -1, "n_verts": 1}
_SHAPE_KEYS = ("verts", "n_verts", "radius", "uid")


# ------------------------------------------------------------------------------ geometry


def world_vertices_np(verts_body, n_verts, pos, angle) -> np.ndarray:
    """Core vertices in the world frame ``[P, V, 2]`` (m); numpy twin of
    :func:`jaxgran.contact.world_vertices`. ``n_verts`` is accepted for symmetry (padded
    slots repeat the last real vertex, so they transform like it)."""
    del n_verts
    v = np.asarray(verts_body, dtype=float)
    a = np.asarray(angle, dtype=float)
    c, s = np.cos(a)[:, None], np.sin(a)[:, None]
    p = np.asarray(pos, dtype=float)
    wx = c * v[..., 0] - s * v[..., 1] + p[:, 0:1]
    wy = s * v[..., 0] + c * v[..., 1] + p[:, 1:2]
    return np.stack([wx, wy], axis=-1)


def particle_outlines(
    verts_world, n_verts, radius, active, n_arc: int = 24
) -> tuple[list[np.ndarray], np.ndarray]:
    """Rounded outlines of the active particles
    (:func:`jaxgran.geometry.spheropolygon_outline`).

    Args:
        verts_world: ``[P, V, 2]`` core vertices in the world frame (m).
        n_verts, radius, active: ``[P]``.
        n_arc: arc segments per full turn (24: six per right-angle corner).

    Returns:
        the outlines (one ``[M_i, 2]`` array per active particle, m) and the indices ``[A]`` of
        the particles they belong to.
    """
    vw = np.asarray(verts_world, dtype=float)
    nv = np.asarray(n_verts).astype(int)
    rad = np.asarray(radius, dtype=float)
    idx = np.flatnonzero(np.asarray(active, dtype=bool))
    return [spheropolygon_outline(vw[i, : nv[i]], rad[i], n_arc) for i in idx], idx


# ------------------------------------------------------------------------------ paths


def _out_path(path) -> Path:
    """Check an output file path and create its folder; errors say what to do."""
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(f"{p} is a directory; give a file name, e.g. {p / 'run.h5'}")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise NotADirectoryError(
            f"cannot create the folder {p.parent} for {p.name} ({exc}); choose another path"
        ) from exc
    return p


# ------------------------------------------------------------------------------ JSON


def _to_jsonable(obj: Any) -> Any:
    """numpy / jax / dataclass / equinox values -> plain JSON types (keys as strings)."""
    if isinstance(obj, Mapping):
        return {str(k): _to_jsonable(v) for k, v in obj.items()}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (str, bool, int, float)) or obj is None:
        return obj
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (set, frozenset)):
        return [_to_jsonable(v) for v in sorted(obj, key=repr)]
    if isinstance(obj, (list, tuple)):
        return [_to_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if hasattr(obj, "__array__"):  # numpy and jax arrays
        return np.asarray(obj).tolist()
    raise TypeError(
        f"cannot store a {type(obj).__name__} as JSON; convert it to numbers, strings, "
        "lists or dicts first"
    )


def write_summary(path: str | os.PathLike, summary: dict) -> None:
    """Write ``summary`` as JSON (sorted keys, indent 2); numpy/jax scalars and arrays,
    dataclasses and paths are converted. Non-finite floats are written as ``NaN`` /
    ``Infinity`` (Python's json reads them back)."""
    p = _out_path(path)
    text = json.dumps(_to_jsonable(summary), sort_keys=True, indent=2)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(text + "\n")
    os.replace(tmp, p)  # never leave a half-written file


# ------------------------------------------------------------------------------ HDF5 helpers


def _put(group: h5py.Group, name: str, data, units: str | None = None, frame_axis=False):
    arr = np.asarray(data)
    if arr.dtype.kind in "US":
        arr = arr.astype(object)
    if arr.dtype == object:
        ds = group.create_dataset(name, data=arr, dtype=h5py.string_dtype())
    elif arr.size > _COMPRESS_ABOVE:
        chunks: Any = True
        per_frame = int(np.prod(arr.shape[1:])) if arr.ndim > 1 else 0
        if frame_axis and per_frame >= _COMPRESS_ABOVE and per_frame * arr.itemsize <= 4 << 20:
            chunks = (1,) + arr.shape[1:]  # one frame per chunk: cheap single-frame reads
        ds = group.create_dataset(
            name, data=arr, chunks=chunks, compression="gzip", compression_opts=4, shuffle=True
        )
    else:
        ds = group.create_dataset(name, data=arr)
    if units:
        ds.attrs["units"] = units
    return ds


def _set_attrs(group: h5py.Group, values: Mapping[str, Any]) -> None:
    """Scalars, strings and numeric arrays as attributes; dicts, lists and None as JSON."""
    json_keys = []
    for key, val in values.items():
        if isinstance(val, (str, bool, int, float, np.generic)):
            group.attrs[key] = val
        elif isinstance(val, np.ndarray) and val.dtype.kind in "biuf":
            group.attrs[key] = val
        else:
            try:
                group.attrs[key] = json.dumps(_to_jsonable(val), sort_keys=True)
            except TypeError as exc:
                raise TypeError(f"metadata {key!r}: {exc}") from exc
            json_keys.append(key)
    if json_keys:
        group.attrs["_json"] = json.dumps(sorted(json_keys))


def _get_attrs(obj) -> dict[str, Any]:
    out = {}
    json_keys = set(json.loads(obj.attrs["_json"])) if "_json" in obj.attrs else set()
    for key, val in obj.attrs.items():
        if key == "_json":
            continue
        if isinstance(val, bytes):
            val = val.decode()
        out[key] = json.loads(val) if key in json_keys else val
    return out


def _module_arrays(module) -> dict[str, np.ndarray]:
    """Array fields of an equinox Module / dataclass as numpy arrays."""
    out = {}
    for f in dataclasses.fields(module):
        val = getattr(module, f.name)
        if hasattr(val, "__array__") or isinstance(val, (int, float, bool)):
            out[f.name] = np.asarray(val)
    return out


# ------------------------------------------------------------------------------ frames


def _pad_particles(arr: np.ndarray, n: int, key: str) -> np.ndarray:
    if arr.shape[0] >= n:
        return arr
    extra = n - arr.shape[0]
    if key == "verts":
        fill = np.zeros((extra,) + arr.shape[1:], arr.dtype)
    else:
        fill = np.full((extra,) + arr.shape[1:], _PARTICLE_PAD.get(key, 0), arr.dtype)
    return np.concatenate([arr, fill], axis=0)


def _pad_vertices(verts: np.ndarray, v: int) -> np.ndarray:
    if verts.shape[1] >= v:
        return verts
    last = verts[:, -1:, :]
    return np.concatenate([verts, np.repeat(last, v - verts.shape[1], axis=1)], axis=1)


def stack_frames(
    frames: Sequence[Mapping[str, Any]], particles: Particles | None = None
) -> dict[str, np.ndarray]:
    """Stack host frames (from :func:`jaxgran.simulate.frame_of`) on a leading frame axis.

    Particle shapes (``verts`` body frame, ``n_verts``, ``radius``, ``uid``) are taken from a
    frame when it has them (breakage changes shapes) and otherwise from ``particles`` (the
    final :class:`~jaxgran.state.Particles`), which is exact only while no particle has
    changed shape. Frames with fewer particle slots are padded with inactive slots, and
    shorter vertex arrays by repeating the last vertex.
    """
    if not frames:
        return {}
    final = _module_arrays(particles) if particles is not None else {}
    filled = []
    for k, fr in enumerate(frames):
        fr = {key: np.asarray(val) for key, val in fr.items()}
        n_p = fr["pos"].shape[0]
        for key in _SHAPE_KEYS:
            if key in fr:
                continue
            if key not in final:
                raise ValueError(
                    f"frame {k} has no {key!r} and no final particles were given to take it from"
                )
            if final[key].shape[0] < n_p:
                raise ValueError(
                    f"frame {k} has {n_p} particle slots but the final state only "
                    f"{final[key].shape[0]}; record {key!r} in such frames"
                )
            fr[key] = final[key][:n_p]
        filled.append(fr)
    keys = [k for k in filled[0] if all(k in fr for fr in filled)]
    dropped = sorted({k for fr in filled for k in fr} - set(keys))
    if dropped:
        log.warning("frame keys %s are missing from some frames and were not stored", dropped)
    n_max = max(fr["pos"].shape[0] for fr in filled)
    v_max = max(fr["verts"].shape[1] for fr in filled)
    out = {}
    for key in keys:
        arrs = []
        for fr in filled:
            a = fr[key]
            per_particle = not key.startswith("wall_") and a.ndim > 0
            per_particle = per_particle and a.shape[0] == fr["pos"].shape[0]
            if key == "verts":
                a = _pad_vertices(a, v_max)
            if per_particle:
                a = _pad_particles(a, n_max, key)
            arrs.append(a)
        try:
            out[key] = np.stack(arrs, axis=0)
        except ValueError as exc:
            shapes = sorted({a.shape for a in arrs})
            raise ValueError(f"frame key {key!r} changes shape between frames: {shapes}") from exc
    return out


# ------------------------------------------------------------------------------ events

_KIND = "kind"


def _is_ragged_list(val) -> bool:
    if not isinstance(val, (list, tuple)) or not val:
        return False
    try:
        return np.asarray(val).dtype == object
    except ValueError:  # numpy refuses inhomogeneous nesting
        return True


def _concat(leaves: list[np.ndarray], field: str) -> np.ndarray:
    tails = {a.shape[1:] for a in leaves}
    if len(tails) > 1:
        raise ValueError(
            f"event field {field!r}: ragged arrays must agree beyond their first axis, "
            f"got trailing shapes {sorted(tails)}"
        )
    if not leaves:
        return np.zeros((0,))
    return np.concatenate(leaves, axis=0)


def _write_events(group: h5py.Group, events: Sequence[Mapping[str, Any]]) -> None:
    """Each field of the log is one dataset ``/events/<field>`` of length ``n_events``
    when every event has it with one shape; otherwise a group with ``data``, ``offsets``
    (``[n + 1]``, ragged arrays flattened along their first axis), ``list_offsets`` (lists
    of ragged arrays) and ``present`` (events that have the field)."""
    group.attrs["n_events"] = len(events)
    fields = sorted({key for ev in events for key in ev})
    missing = object()
    for name in fields:
        vals = [ev.get(name, missing) for ev in events]
        present = np.array([v is not missing for v in vals])
        got = [v for v in vals if v is not missing]
        if all(isinstance(v, str) for v in got):
            if present.all():
                _put(group, name, np.array(got, dtype=object))
            else:
                sub = group.create_group(name)
                sub.attrs[_KIND] = "sparse"
                _put(sub, "data", np.array(got, dtype=object))
                _put(sub, "present", present)
            continue
        if any(_is_ragged_list(v) for v in got):
            sub = group.create_group(name)
            sub.attrs[_KIND] = "ragged_list"
            leaves, counts = [], []
            for v in got:
                items = [np.atleast_1d(np.asarray(x)) for x in v]
                leaves += items
                counts.append(len(items))
            _put(sub, "data", _concat(leaves, name), UNITS.get(name))
            _put(sub, "offsets", np.concatenate([[0], np.cumsum([len(a) for a in leaves])]))
            _put(sub, "list_offsets", np.concatenate([[0], np.cumsum(counts)]))
            _put(sub, "present", present)
            continue
        arrs = [np.asarray(v) for v in got]
        if any(a.dtype == object for a in arrs):
            raise TypeError(
                f"event field {name!r} holds values h5py cannot store; use numbers, strings, "
                "arrays or lists of arrays"
            )
        if len({a.shape for a in arrs}) == 1:
            data = np.stack(arrs) if arrs else np.zeros((0,))
            if present.all():
                _put(group, name, data, UNITS.get(name))
            else:
                sub = group.create_group(name)
                sub.attrs[_KIND] = "sparse"
                _put(sub, "data", data, UNITS.get(name))
                _put(sub, "present", present)
            continue
        leaves = [np.atleast_1d(a) for a in arrs]
        sub = group.create_group(name)
        sub.attrs[_KIND] = "ragged"
        _put(sub, "data", _concat(leaves, name), UNITS.get(name))
        _put(sub, "offsets", np.concatenate([[0], np.cumsum([len(a) for a in leaves])]))
        _put(sub, "present", present)


def _read_events(group: h5py.Group) -> list[dict[str, Any]]:
    n = int(group.attrs.get("n_events", 0))
    events: list[dict[str, Any]] = [{} for _ in range(n)]
    for name, obj in group.items():
        if isinstance(obj, h5py.Dataset):
            data = obj.asstr()[()] if h5py.check_string_dtype(obj.dtype) else obj[()]
            for i in range(n):
                val = data[i]
                events[i][name] = str(val) if isinstance(val, bytes | str) else val
            continue
        kind = obj.attrs[_KIND]
        present = obj["present"][()]
        data_ds = obj["data"]
        is_str = h5py.check_string_dtype(data_ds.dtype) is not None
        data = data_ds.asstr()[()] if is_str else data_ds[()]
        rows = np.flatnonzero(present)
        if kind == "sparse":
            vals = [str(d) if is_str else d for d in data]
        elif kind == "ragged":
            off = obj["offsets"][()]
            vals = [data[off[j] : off[j + 1]] for j in range(len(rows))]
        elif kind == "ragged_list":
            off = obj["offsets"][()]
            loff = obj["list_offsets"][()]
            vals = [
                [data[off[m] : off[m + 1]] for m in range(loff[j], loff[j + 1])]
                for j in range(len(rows))
            ]
        else:
            raise ValueError(f"unknown event field layout {kind!r} for {name!r}")
        for i, val in zip(rows, vals, strict=True):
            events[i][name] = val
    return events


# ------------------------------------------------------------------------------ run files


def _versions() -> dict[str, str]:
    import jax

    from . import __version__

    return {
        "jaxgran_version": __version__,
        "jax_version": jax.__version__,
        "numpy_version": np.__version__,
        "h5py_version": h5py.__version__,
    }


def write_run(
    path: str | os.PathLike,
    result: RunResult,
    params: Params,
    *,
    metadata: dict | None = None,
    events: list[dict] | None = None,
) -> None:
    """Write a whole run to one HDF5 file (layout in the module docstring).

    Args:
        path: file to write (its folder is created); an existing file is replaced.
        result: :class:`jaxgran.simulate.RunResult`.
        params: :class:`jaxgran.state.Params` of the run.
        metadata: JSON-serialisable extras; ``scene`` names the scene. Nested dicts and lists
            are stored as JSON strings and decoded by :func:`read_run`.
        events: event log (breakage, bond breaks, ...), one dict per event with scalar, string,
            array or list-of-array values. A field whose arrays differ in length is stored
            flattened along the first axis with ``offsets``; events may lack fields.

    Frames recorded without particle shapes take ``verts``/``n_verts``/``radius``/``uid``
    from the final state (attr ``/frames.shapes_from_final_state`` says so); frames that hold
    these keys (recorded after breakage) are stored as they are.
    """
    p = _out_path(path)
    state = result.state
    particles = state.particles
    frames = stack_frames(result.frames, particles)
    tmp = p.with_name(p.name + ".tmp")
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT_NAME
            f.attrs["format_version"] = FORMAT_VERSION

            g = f.create_group("params")
            for name, val in _module_arrays(params).items():
                if val.ndim == 0:
                    g.attrs[name] = val
                else:
                    _put(g, name, val, PARAM_UNITS.get(name))
            g.attrs["units"] = json.dumps(PARAM_UNITS, sort_keys=True)

            meta = {
                "scene": "",
                **_versions(),
                "dtype": str(np.asarray(particles.pos).dtype),
                "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "steps": int(result.steps),
                "wall_time_s": float(result.wall_time_s),
                "stopped_early": bool(result.stopped_early),
                "regrows": list(result.regrows),
                "grid": result.grid,
            }
            meta.update(metadata or {})
            _set_attrs(f.create_group("metadata"), meta)

            g = f.create_group("series")
            for name, val in result.series.items():
                _put(g, name, val, UNITS.get(name))

            g = f.create_group("frames")
            g.attrs["n_frames"] = len(result.frames)
            g.attrs["shapes_from_final_state"] = bool(
                result.frames and any("verts" not in fr for fr in result.frames)
            )
            for name, val in frames.items():
                _put(g, name, val, UNITS.get(name), frame_axis=True)

            _write_events(f.create_group("events"), list(events or []))

            g = f.create_group("final")
            g.attrs["time"] = np.asarray(state.time)
            g.attrs["step"] = np.asarray(state.step)
            for name, val in _module_arrays(particles).items():
                _put(g, name, val, UNITS.get(name))
            gw = g.create_group("walls")
            for name, val in _module_arrays(state.walls).items():
                _put(gw, name, val, UNITS.get(name))
            if state.bonds is not None:
                gb = g.create_group("bonds")
                for name, val in _module_arrays(state.bonds).items():
                    _put(gb, name, val)
        os.replace(tmp, p)  # never leave a half-written file
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _read_group(group: h5py.Group, units: dict[str, str], prefix: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, obj in group.items():
        if isinstance(obj, h5py.Group):
            out[name] = _read_group(obj, units, f"{prefix}/{name}")
        elif h5py.check_string_dtype(obj.dtype):
            out[name] = obj.asstr()[()]
        else:
            out[name] = obj[()]
        if "units" in obj.attrs and isinstance(obj, h5py.Dataset):
            units[f"{prefix}/{name}"] = str(obj.attrs["units"])
    return out


def read_run(path: str | os.PathLike) -> dict[str, Any]:
    """Read a file written by :func:`write_run` into plain Python.

    Returns:
        ``{"params": {...}, "metadata": {...}, "series": {...}, "frames": {...},
        "frames_attrs": {...}, "events": [dict, ...], "final": {..., "walls": {...}},
        "final_attrs": {...}, "units": {"series/time": "s", ...}, "attrs": {...}}``
        with numpy arrays; ``events`` is the list of event dicts that was written (a ragged
        field comes back as arrays, 0-d values of a ragged field as length-1 arrays).
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no run file at {p}; write one with jaxgran.io.write_run")
    if p.is_dir():
        raise IsADirectoryError(f"{p} is a directory; give the run file, e.g. {p / 'run.h5'}")
    if not h5py.is_hdf5(p):
        raise ValueError(f"{p} is not an HDF5 file (expected a run file from write_run)")
    with h5py.File(p, "r") as f:
        if f.attrs.get("format") != FORMAT_NAME:
            raise ValueError(f"{p} is HDF5 but not a jaxgran run file (no format attribute)")
        version = int(f.attrs["format_version"])
        if version > FORMAT_VERSION:
            raise ValueError(
                f"{p} has run-file format {version}, newer than this jaxgran reads "
                f"({FORMAT_VERSION}); upgrade jaxgran"
            )
        units: dict[str, str] = {}
        out: dict[str, Any] = {"attrs": _get_attrs(f)}
        params = {k: v for k, v in _get_attrs(f["params"]).items() if k != "units"}
        params.update(_read_group(f["params"], units, "params"))
        out["params"] = params
        out["metadata"] = _get_attrs(f["metadata"])
        out["series"] = _read_group(f["series"], units, "series")
        out["frames"] = _read_group(f["frames"], units, "frames")
        out["frames_attrs"] = _get_attrs(f["frames"])
        out["events"] = _read_events(f["events"])
        out["final"] = _read_group(f["final"], units, "final")
        out["final_attrs"] = _get_attrs(f["final"])
        out["units"] = units
    return out


def params_from_run(run: Mapping[str, Any]) -> Params:
    """Rebuild :class:`jaxgran.state.Params` from ``read_run(path)["params"]``."""
    import jax.numpy as jnp

    from .state import Params

    names = [f.name for f in dataclasses.fields(Params)]
    missing = [n for n in names if n not in run["params"]]
    if missing:
        raise KeyError(f"run file lacks parameters {missing}; was it written by an older jaxgran?")
    return Params(**{n: jnp.asarray(run["params"][n]) for n in names})


# ------------------------------------------------------------------------------ VTK


def _run_frames(run) -> dict[str, np.ndarray]:
    if isinstance(run, Mapping):
        frames = run.get("frames") or {}
        return {k: np.asarray(v) for k, v in frames.items()}
    return stack_frames(run.frames, run.state.particles)


def _frame_geometry(frames: Mapping[str, np.ndarray], k: int, n_arc: int):
    vw = world_vertices_np(
        frames["verts"][k], frames["n_verts"][k], frames["pos"][k], frames["angle"][k]
    )
    outlines, idx = particle_outlines(
        vw, frames["n_verts"][k], frames["radius"][k], frames["active"][k], n_arc
    )
    speed = np.linalg.norm(frames["vel"][k][idx], axis=-1)
    fmag = np.linalg.norm(frames["force"][k][idx], axis=-1)
    uid = frames["uid"][k][idx].astype(np.int64)
    return outlines, {"uid": uid, "speed": speed, "force_magnitude": fmag}


def _fmt(values: np.ndarray, per_line: int) -> str:
    flat = np.asarray(values).ravel()
    fmt = "%d" if flat.dtype.kind in "iub" else "%.9g"
    rows = [
        " ".join(fmt % x for x in flat[i : i + per_line]) for i in range(0, len(flat), per_line)
    ]
    return "\n".join(rows)


def _legacy_vtk(outlines, cell: dict[str, np.ndarray], title: str) -> str:
    pts = np.concatenate(outlines) if outlines else np.zeros((0, 2))
    pts3 = np.column_stack([pts, np.zeros(len(pts))])
    lines = [
        "# vtk DataFile Version 3.0",
        title[:255],
        "ASCII",
        "DATASET POLYDATA",
        f"POINTS {len(pts3)} double",
        _fmt(pts3, 3),
    ]
    start = 0
    conn = []
    for o in outlines:
        conn.append(" ".join(map(str, [len(o), *range(start, start + len(o))])))
        start += len(o)
    lines.append(f"POLYGONS {len(outlines)} {len(outlines) + start}")
    lines += conn
    lines.append(f"CELL_DATA {len(outlines)}")
    for name, val in cell.items():
        kind = "int" if val.dtype.kind in "iub" else "double"
        lines += [f"SCALARS {name} {kind} 1", "LOOKUP_TABLE default", _fmt(val, 9)]
    return "\n".join(line for line in lines if line != "") + "\n"


def _xml_vtp(outlines, cell: dict[str, np.ndarray]) -> str:
    pts = np.concatenate(outlines) if outlines else np.zeros((0, 2))
    pts3 = np.column_stack([pts, np.zeros(len(pts))])
    sizes = np.array([len(o) for o in outlines], dtype=np.int64)
    conn = np.arange(int(sizes.sum()), dtype=np.int64)

    def array(name, val, comps=1):
        kind = "Int64" if val.dtype.kind in "iub" else "Float64"
        return (
            f'<DataArray type="{kind}" Name="{name}" NumberOfComponents="{comps}" '
            f'format="ascii">\n{_fmt(val, 3 * comps if comps > 1 else 9)}\n</DataArray>'
        )

    cells = "\n".join(array(n, v) for n, v in cell.items())
    return (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian">\n<PolyData>\n'
        f'<Piece NumberOfPoints="{len(pts3)}" NumberOfVerts="0" NumberOfLines="0" '
        f'NumberOfStrips="0" NumberOfPolys="{len(outlines)}">\n'
        f"<Points>\n{array('points', pts3, 3)}\n</Points>\n"
        f"<Polys>\n{array('connectivity', conn)}\n{array('offsets', np.cumsum(sizes))}\n"
        "</Polys>\n"
        f'<CellData Scalars="speed">\n{cells}\n</CellData>\n'
        "</Piece>\n</PolyData>\n</VTKFile>\n"
    )


def write_vtk(
    path_prefix: str | os.PathLike,
    run: Mapping[str, Any] | RunResult,
    every: int = 1,
    *,
    fmt: str = "vtk",
    n_arc: int = 24,
) -> list[Path]:
    """Write frames for ParaView, one polygon per active particle (its rounded outline).

    Cell data: ``uid``, ``speed`` (m/s) and ``force_magnitude`` |F| (N, net force).

    Args:
        path_prefix: ``out/run`` gives ``out/run_00000.vtk``, ... (the folder is created).
        run: ``read_run(path)`` or a :class:`~jaxgran.simulate.RunResult`.
        every: write every this many frames.
        fmt: ``"vtk"``: legacy ASCII POLYDATA files plus a ``<prefix>.vtk.series`` file (the
            JSON file-series format ParaView >= 5.5 opens with the frame times; a ``.pvd``
            cannot list legacy files, ParaView's PVD reader opens only XML ones);
            ``"vtp"``: XML ASCII PolyData files plus a ``<prefix>.pvd`` collection.
        n_arc: arc segments per full turn of a rounded corner.

    Returns:
        the frame files, then the collection file.
    """
    if fmt not in ("vtk", "vtp"):
        raise ValueError(f"fmt must be 'vtk' (legacy) or 'vtp' (XML), got {fmt!r}")
    if int(every) < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    frames = _run_frames(run)
    if not frames:
        raise ValueError("the run has no frames to write; record frames with simulate()")
    prefix = Path(path_prefix)
    _out_path(prefix.with_name(prefix.name + f"_00000.{fmt}"))
    written: list[Path] = []
    times = []
    n_frames = frames["pos"].shape[0]
    for k in range(0, n_frames, int(every)):
        outlines, cell = _frame_geometry(frames, k, n_arc)
        t = float(frames["time"][k]) if "time" in frames else float(k)
        out = prefix.with_name(f"{prefix.name}_{k:05d}.{fmt}")
        if fmt == "vtk":
            out.write_text(_legacy_vtk(outlines, cell, f"jaxgran frame {k} time {t:.9g} s"))
        else:
            out.write_text(_xml_vtp(outlines, cell))
        written.append(out)
        times.append(t)
    if fmt == "vtk":
        coll = prefix.with_name(prefix.name + ".vtk.series")
        files = [{"name": w.name, "time": t} for w, t in zip(written, times, strict=True)]
        coll.write_text(json.dumps({"file-series-version": "1.0", "files": files}, indent=1))
    else:
        coll = prefix.with_name(prefix.name + ".pvd")
        rows = "\n".join(
            f'    <DataSet timestep="{t:.12g}" group="" part="0" file="{w.name}"/>'
            for w, t in zip(written, times, strict=True)
        )
        coll.write_text(
            '<?xml version="1.0"?>\n'
            '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
            f"  <Collection>\n{rows}\n  </Collection>\n</VTKFile>\n"
        )
    return written + [coll]


# ---------------------------------------------------------------------------------------------
# checkpoints of long runs
# ---------------------------------------------------------------------------------------------

CHECKPOINT_FORMAT = 1


def save_checkpoint(path: str | os.PathLike, key: Any, payload: Any) -> None:
    """Pickle ``payload`` (states, a breakage handler, lists of records...) to ``path``
    atomically (a partial file never replaces a good one), tagged with ``key`` (e.g. the
    scene's configuration) so that :func:`load_checkpoint` refuses another run's file.
    JAX arrays are stored as NumPy arrays and come back as JAX arrays of the same dtype."""
    import pickle

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "wb") as fh:
        pickle.dump(
            {"format": CHECKPOINT_FORMAT, "key": key, "payload": payload},
            fh,
            protocol=pickle.HIGHEST_PROTOCOL,
        )
    os.replace(tmp, path)


def read_checkpoint(path: str | os.PathLike) -> tuple[Any, Any]:
    """``(key, payload)`` of a file written by :func:`save_checkpoint`, the key not checked
    against any run (for a progress report); raises ``ValueError`` for another format
    version. Only read files you wrote: this unpickles."""
    import pickle

    with open(path, "rb") as fh:
        try:
            blob = pickle.load(fh)
        except Exception as exc:  # a truncated or foreign file: pickle raises many kinds
            raise SceneError(
                f"{path}: not a jaxgran checkpoint (it cannot be unpickled: {type(exc).__name__})"
            ) from exc
    if not isinstance(blob, dict) or blob.get("format") != CHECKPOINT_FORMAT:
        raise SceneError(f"{path}: not a jaxgran checkpoint of format {CHECKPOINT_FORMAT}")
    return blob["key"], blob["payload"]


def load_checkpoint(path: str | os.PathLike, key: Any) -> Any:
    """The payload saved by :func:`save_checkpoint` at ``path``. Raises ``ValueError`` if
    the file was written by another format version or for another ``key`` (a checkpoint of
    a run with other settings must not be continued silently). Only load files you wrote:
    this unpickles."""
    saved_key, payload = read_checkpoint(path)
    if saved_key != key:
        raise SceneError(
            f"{path}: the checkpoint belongs to a run with other settings; delete it or run "
            "without resume"
        )
    return payload
