"""Ensemble axis sharded over devices (jaxgran.ensemble.shard / drive(mesh=...)): two host
devices give the same run as one, to 1e-12 in float64. The device count is fixed when JAX
starts, so the check runs in a subprocess with XLA_FLAGS set."""

import json
import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import dataclasses, json
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from jaxgran import ensemble as ens
    from jaxgran.scenes import bonded_brazilian as bz

    cfg = dataclasses.replace(
        bz.Config(), n_cells=30, strain_rate=40.0, record_every=25, records_per_segment=4
    )
    setup = bz.build(cfg, seeds=[0, 1])
    state, control = ens.stack(setup.states), ens.stack(setup.controls)
    kw = dict(n_steps=400, record_every=25, records_per_segment=4, batched=True,
              progress=False)
    plain = ens.drive(state, setup.params, control, setup.grid, **kw)
    mesh = ens.ensemble_mesh()
    sharded = ens.drive(state, setup.params, control, setup.grid, mesh=mesh, **kw)
    pos = sharded.state.particles.pos
    ref = np.asarray(plain.state.particles.pos)
    diff = lambda a, b: float(np.abs(np.asarray(a) - np.asarray(b)).max())
    out = {
        "devices": len(jax.devices()),
        "mesh": int(mesh.shape["realisation"]),
        "pos_devices": len(pos.sharding.device_set),
        "max_pos_diff": diff(pos, ref),
        "max_force_diff": diff(sharded.series["wall_force"], plain.series["wall_force"]),
        "force_scale": float(np.abs(plain.series["wall_force"]).max()),
        "builds": np.asarray(plain.state.contacts.n_builds).tolist(),
        "moved": diff(ref, state.particles.pos),
    }
    try:
        ens.shard(ens.stack(setup.states + setup.states[:1]), mesh)
        out["uneven"] = "accepted"
    except ValueError as exc:
        out["uneven"] = str(exc)
    print("RESULT" + json.dumps(out))
    """
)


def test_sharded_ensemble_equals_unsharded():
    env = dict(os.environ)
    env["XLA_FLAGS"] = env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    env["JAX_PLATFORMS"] = "cpu"
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT")][-1]
    r = json.loads(line[len("RESULT") :])
    assert r["devices"] == 2 and r["mesh"] == 2
    assert r["pos_devices"] == 2  # the result really lives on both devices
    assert r["moved"] > 1e-5  # the platens have loaded the discs
    assert r["max_pos_diff"] <= 1e-12 * 0.05  # m, relative to the disc size D = 0.1 m
    assert r["max_force_diff"] <= 1e-12 * r["force_scale"]
    assert "multiple of 2" in r["uneven"]
