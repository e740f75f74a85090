"""Run files (HDF5), VTK output, summaries and figures, on a tiny hand-made run."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import io
from jaxgran.contact import world_vertices
from jaxgran.simulate import RunResult, frame_of
from jaxgran.state import (
    Grid,
    box_walls,
    make_params,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
)

SIDE, R_SQUARE = 0.01, 0.001  # m


def _state():
    square = np.array([[0, 0], [SIDE, 0], [SIDE, SIDE], [0, SIDE]]) + [0.01, 0.01]
    tri = np.array([[0.0, 0.0], [0.008, 0.0], [0.004, 0.007]]) + [0.03, 0.01]
    disc = np.array([[0.02, 0.035]])
    parts = particles_from_polygons(
        [square, tri, disc], [R_SQUARE, 0.0005, 0.004], 2650.0, capacity=4, vertex_capacity=4
    )
    walls = make_walls(box_walls((0.0, 0.0), (0.05, 0.05), top=False))
    return make_state(parts, walls)


def _run(n_records=1500):
    state = _state()
    frames = []
    for k in range(3):
        p = state.particles
        p = replace(
            p,
            pos=p.pos + 1e-3 * k,
            angle=p.angle + 0.1 * k,
            vel=p.vel + 0.01 * (k + 1),
            force=p.force + jnp.array([0.0, -1.0]) * (jnp.arange(4)[:, None] + k),
        )
        s = replace(state, particles=p, time=jnp.asarray(0.01 * k))
        fr = frame_of(s)
        if k < 2:  # older frames without shapes: the writer takes them from the final state
            for key in ("verts", "n_verts", "radius", "uid"):
                fr.pop(key)
        if k == 2:  # as if a particle had broken: the frame carries its own shapes
            fr["verts"] = np.asarray(p.verts) * 0.5
            fr["n_verts"] = np.asarray(p.n_verts)
            fr["radius"] = np.asarray(p.radius)
            fr["uid"] = np.asarray(p.uid) + 10
        frames.append(fr)
    state = replace(state, time=jnp.asarray(0.02))
    t = np.linspace(0.0, 0.02, n_records)
    rng = np.random.default_rng(0)
    n_w = state.walls.point.shape[0]
    series = {
        "time": t,
        "kinetic_energy": np.exp(-t / 0.005),
        "rotational_energy": 0.1 * np.exp(-t / 0.005),
        "mean_speed": np.exp(-t),
        "mean_angular_speed": np.exp(-t),
        "wall_point": np.broadcast_to(np.asarray(state.walls.point), (n_records, n_w, 2)).copy(),
        "wall_force": rng.normal(size=(n_records, n_w, 2)),
        "n_active": np.full(n_records, 3, dtype=np.int32),
    }
    grid = Grid(origin=(0.0, 0.0), cell_size=0.02, nx=3, ny=3, cell_capacity=4)
    return RunResult(
        state=state,
        series=series,
        frames=frames,
        grid=grid,
        steps=1500,
        wall_time_s=1.25,
        regrows=["pair capacity 4 exceeded; grown to 8"],
    )


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("run") / "sub" / "run.h5"
    result = _run()
    params = make_params(dt=1e-6)
    meta = {"scene": "tiny", "seed": 3, "loading": {"rate": 0.1, "stages": [1, 2]}}
    io.write_run(path, result, params, metadata=meta)
    return path, result, params


def test_round_trip(run_file):
    path, result, params = run_file
    run = io.read_run(path)
    for name, val in result.series.items():
        np.testing.assert_array_equal(run["series"][name], val)
    for name in ("time", "pos", "angle", "vel", "omega", "force", "active", "wall_force"):
        np.testing.assert_array_equal(
            run["frames"][name], np.stack([fr[name] for fr in result.frames])
        )
    p = result.state.particles
    assert run["frames"]["verts"].shape == (3, 4, 4, 2)
    np.testing.assert_array_equal(run["frames"]["verts"][0], p.verts)  # from the final state
    np.testing.assert_array_equal(run["frames"]["verts"][2], 0.5 * np.asarray(p.verts))
    np.testing.assert_array_equal(run["frames"]["uid"][2], np.asarray(p.uid) + 10)
    np.testing.assert_array_equal(run["frames"]["n_verts"][1], p.n_verts)
    assert run["frames_attrs"]["shapes_from_final_state"]
    for name in ("verts", "n_verts", "radius", "mass", "inertia", "pos", "active", "uid"):
        np.testing.assert_array_equal(run["final"][name], getattr(p, name))
    np.testing.assert_array_equal(run["final"]["walls"]["normal"], result.state.walls.normal)
    assert run["final_attrs"]["time"] == pytest.approx(0.02)
    for name in ("normal_stiffness", "dt", "friction", "gravity"):
        np.testing.assert_array_equal(run["params"][name], getattr(params, name))
    rebuilt = io.params_from_run(run)
    assert float(rebuilt.dt) == 1e-6
    meta = run["metadata"]
    assert meta["scene"] == "tiny" and meta["seed"] == 3
    assert meta["loading"] == {"rate": 0.1, "stages": [1, 2]}
    assert meta["grid"]["cell_capacity"] == 4 and meta["regrows"] == result.regrows
    assert meta["dtype"] == "float64" and meta["steps"] == 1500
    for key in ("jaxgran_version", "jax_version", "date"):
        assert meta[key]
    assert run["units"]["frames/pos"] == "m" and run["units"]["series/kinetic_energy"] == "J"
    assert run["units"]["series/time"] == "s" and run["units"]["frames/force"] == "N"
    assert run["events"] == []
    with h5py.File(path) as f:
        assert f["series/time"].compression == "gzip"  # 1500 elements
        assert f["series/wall_force"].chunks is not None
        assert f["final/mass"].compression is None  # small
        assert f["frames/pos"].attrs["units"] == "m"


def test_events_round_trip_ragged(tmp_path):
    events = [
        {
            "kind": "breakage",
            "time": 0.1,
            "uid": 3,
            "points": np.arange(6.0).reshape(3, 2),
            "fragments": [np.ones((3, 2)), np.zeros((5, 2))],
            "centre": np.array([0.1, 0.2]),
        },
        {
            "kind": "bond_break",
            "time": 0.2,
            "uid": 7,
            "points": np.zeros((0, 2)),
            "centre": np.array([0.3, 0.4]),
        },
        {
            "kind": "breakage",
            "time": 0.3,
            "uid": 9,
            "points": np.full((1, 2), 2.0),
            "fragments": [np.full((4, 2), 3.0), np.full((3, 2), 4.0), np.full((3, 2), 5.0)],
            "centre": np.array([0.5, 0.6]),
        },
    ]
    path = tmp_path / "run.h5"
    io.write_run(path, _run(10), make_params(), events=events)
    back = io.read_run(path)["events"]
    assert len(back) == 3
    for ev, got in zip(events, back, strict=True):
        assert set(got) == set(ev)
        for key, val in ev.items():
            if key == "fragments":
                assert len(got[key]) == len(val)
                for a, b in zip(got[key], val, strict=True):
                    np.testing.assert_array_equal(a, b)
            elif isinstance(val, str):
                assert got[key] == val
            else:
                np.testing.assert_array_equal(got[key], val)
    with h5py.File(path) as f:
        assert f["events/time"].shape == (3,)
        np.testing.assert_array_equal(f["events/points/offsets"][()], [0, 3, 3, 4])
        assert f["events/points/data"].shape == (4, 2)
        np.testing.assert_array_equal(f["events/fragments/present"][()], [True, False, True])


def test_frames_with_grown_capacity_are_padded():
    state = _state()
    small = frame_of(state)
    big = {
        k: np.concatenate([v, v[:2]]) if k not in ("time",) and not k.startswith("wall") else v
        for k, v in frame_of(state).items()
    }
    p = state.particles
    big["verts"] = np.concatenate([np.asarray(p.verts), np.asarray(p.verts)[:2]])[:, :3]
    big["n_verts"] = np.concatenate([np.asarray(p.n_verts), [3, 3]])
    big["radius"] = np.concatenate([np.asarray(p.radius), [0.001, 0.001]])
    big["uid"] = np.arange(6)
    stacked = io.stack_frames([small, big], p)
    assert stacked["pos"].shape == (2, 6, 2)
    assert stacked["verts"].shape == (2, 6, 4, 2)
    assert not stacked["active"][0, 4:].any() and (stacked["uid"][0, 4:] == -1).all()
    np.testing.assert_array_equal(stacked["verts"][1, :, 3], stacked["verts"][1, :, 2])


def test_world_vertices_twin():
    state = _state()
    p = replace(state.particles, angle=jnp.array([0.3, -1.0, 2.0, 0.0]))
    np.testing.assert_allclose(
        io.world_vertices_np(p.verts, p.n_verts, p.pos, p.angle), world_vertices(p), atol=1e-15
    )


def _parse_legacy(path):
    text = path.read_text()
    n_pts = int(re.search(r"POINTS (\d+) double", text).group(1))
    m = re.search(r"POLYGONS (\d+) (\d+)\n", text)
    n_poly, size = int(m.group(1)), int(m.group(2))
    body = text[m.end() :].splitlines()
    polys = [list(map(int, line.split()))[1:] for line in body[:n_poly]]
    assert size == n_poly + sum(len(q) for q in polys)
    pts_text = text[text.index("double\n") + 7 : m.start()].split()
    pts = np.array(pts_text, dtype=float).reshape(n_pts, 3)
    assert f"CELL_DATA {n_poly}" in text
    cells = {}
    for name in ("uid", "speed", "force_magnitude"):
        after = text[text.index(f"SCALARS {name}") :].split("LOOKUP_TABLE default", 1)[1]
        cells[name] = np.array(after.split()[:n_poly], dtype=float)
        assert len(cells[name]) == n_poly
    return pts, polys, cells


def _shoelace(xy):
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)


def test_write_vtk_legacy(run_file, tmp_path):
    path, result, _ = run_file
    run = io.read_run(path)
    files = io.write_vtk(tmp_path / "vtk" / "run", run, every=2)
    assert [f.name for f in files] == ["run_00000.vtk", "run_00002.vtk", "run.vtk.series"]
    series = json.loads(files[-1].read_text())
    assert [e["name"] for e in series["files"]] == ["run_00000.vtk", "run_00002.vtk"]
    assert [e["time"] for e in series["files"]] == pytest.approx([0.0, 0.02])
    for f, k in zip(files[:-1], (0, 2), strict=True):
        pts, polys, cells = _parse_legacy(f)
        n_active = int(run["frames"]["active"][k].sum())
        assert len(polys) == n_active == 3
        assert max(max(q) for q in polys) == len(pts) - 1
        np.testing.assert_array_equal(cells["uid"], run["frames"]["uid"][k][:3])
        np.testing.assert_allclose(
            cells["force_magnitude"], np.linalg.norm(run["frames"]["force"][k][:3], axis=-1)
        )
    # the outline of the rounded square encloses its area (a^2 + 4 a r + pi r^2), minus the
    # small chord error of the arcs, and is counter-clockwise
    pts, polys, _ = _parse_legacy(files[0])
    area = _shoelace(pts[polys[0], :2])
    exact = SIDE**2 + 4 * SIDE * R_SQUARE + np.pi * R_SQUARE**2
    assert 0.995 * exact < area < exact


def test_write_vtk_xml_from_result(run_file, tmp_path):
    _, result, _ = run_file
    files = io.write_vtk(tmp_path / "run", result, fmt="vtp")
    assert files[-1].suffix == ".pvd" and len(files) == 4
    coll = ET.parse(files[-1]).getroot()
    sets = coll.find("Collection").findall("DataSet")
    assert [d.get("file") for d in sets] == [f.name for f in files[:-1]]
    assert [float(d.get("timestep")) for d in sets] == pytest.approx([0.0, 0.01, 0.02])
    piece = ET.parse(files[0]).getroot().find("PolyData/Piece")
    assert int(piece.get("NumberOfPolys")) == 3
    offsets = piece.find("Polys/DataArray[@Name='offsets']").text.split()
    assert int(offsets[-1]) == int(piece.get("NumberOfPoints"))
    with pytest.raises(ValueError, match="fmt"):
        io.write_vtk(tmp_path / "x", result, fmt="vtu")


def test_plots(run_file, tmp_path):
    from jaxgran import plot

    path, _, _ = run_file
    run = io.read_run(path)
    paths = plot.plot_run(run, tmp_path / "fig")
    assert sorted(p.name for p in paths) == ["kinetic_energy.png", "packing.png", "wall_forces.png"]
    paths.append(plot.plot_frames(run, tmp_path / "fig", [0, -1], name="evolution"))
    x = np.linspace(0, 1, 5)
    paths.append(plot.plot_series(x, {"a": x, "b": x**2}, "x", "y", tmp_path / "s.png"))
    for p in paths:
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 2000


def test_write_summary(tmp_path):
    path = tmp_path / "out" / "summary.json"
    io.write_summary(
        path,
        {"z": np.float32(1.5), "a": np.arange(3), "n": np.int64(4), "nested": {"b": jnp.ones(2)}},
    )
    text = path.read_text()
    assert text.index('"a"') < text.index('"n"') < text.index('"z"')
    assert json.loads(text) == {"a": [0, 1, 2], "n": 4, "nested": {"b": [1.0, 1.0]}, "z": 1.5}
    with pytest.raises(TypeError, match="JSON"):
        io.write_summary(path, {"bad": object()})


def test_bad_paths(run_file, tmp_path):
    path, result, params = run_file
    with pytest.raises(FileNotFoundError, match="no run file"):
        io.read_run(tmp_path / "missing.h5")
    not_h5 = tmp_path / "notes.txt"
    not_h5.write_text("hello")
    with pytest.raises(ValueError, match="not an HDF5 file"):
        io.read_run(not_h5)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = 1
    with pytest.raises(ValueError, match="not a jaxgran run file"):
        io.read_run(other)
    with pytest.raises(IsADirectoryError, match="is a directory"):
        io.write_run(tmp_path, result, params)
    with pytest.raises(NotADirectoryError, match="cannot create the folder"):
        io.write_run(not_h5 / "run.h5", result, params)
    with pytest.raises(TypeError, match="metadata 'bad'"):
        io.write_run(tmp_path / "r.h5", result, params, metadata={"bad": object()})
    assert not (tmp_path / "r.h5").exists() and not (tmp_path / "r.h5.tmp").exists()
