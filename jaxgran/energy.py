"""Energy balance of a run: what the boundaries and body forces put in, what is stored,
what is dissipated and what breakage releases.

Attach a ledger (:func:`attach`) to a state and every step accumulates, in
:class:`jaxgran.state.EnergyLedger` (J, on a slab of the scene's thickness):

- **boundary work**: the force the walls exert on the particles (contacts and wall bonds),
  trapezoid over the wall's displacement in the step;
- **body work**: gravity, ``m g . dx`` (exact for a constant force), and the body forces
  a scene's control applies as velocity kicks (their kinetic-energy change);
- **dashpot** and **friction**: per contact and step (:func:`jaxgran.contact.contact_law`),
  the dashpot force (applied force minus its spring part, so a normal force clamped at zero
  counts too) times the relative velocity the dashpots use, and the Coulomb slip, what
  the tangential spring loses beyond the work of its force in a slipping step (in steady
  sliding the force at the cap times the slip displacement; also the spring energy a
  falling cap releases);
- **damping**: the kinetic energy a scene's background velocity damping removes;
- **breakage**: the elastic energy a bond loses when it softens or breaks (the step
  updates health before it applies the bond forces, so the loss is exact at the drifted
  positions), and, for a host-side particle replacement, the mechanical energy (kinetic +
  contact elastic) of the state before minus after (:func:`account_host_change`).

The stored energy is kinetic + contact elastic (``K_n delta^2 / 2 + K_t |xi|^2 / 2``) +
bond elastic (:func:`jaxgran.bonds.bond_energy` and the wall bonds). :func:`balance` checks

``boundary_work + body_work = (stored - stored0) + dashpot + friction + damping + breakage``.

Each side is measured on its own; the residual is the error of the explicit scheme (second
order in dt; ``docs/stability.md``) and of the slip and dashpot quadratures. The step
computes the ledger only when one is attached (its presence is static, like the bonds), so a
run without one pays nothing.

Supported: particles with or without paper-002 bonds (:class:`jaxgran.bonds.Bonds`). The
interface bonds of paper 003 carry their own dashpots and damage law, which the ledger does
not yet read: :func:`attach` refuses them rather than report a balance with a missing term.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .bonds import Bonds, bond_energy, wall_bond_energy
from .contact import pair_forces, wall_forces
from .partition import build_pairs
from .state import EnergyLedger, Grid, Params, SimState, replace

__all__ = [
    "account_host_change",
    "attach",
    "balance",
    "control_terms",
    "kinetic_energy",
    "stored_energy",
]


def kinetic_energy(state: SimState) -> jax.Array:
    """Translational + rotational kinetic energy of the active particles (J)."""
    p = state.particles
    e = 0.5 * p.mass * jnp.sum(p.vel**2, axis=-1) + 0.5 * p.inertia * p.omega**2
    return jnp.sum(jnp.where(p.active, e, 0.0))


def _contact_elastic(state: SimState, params: Params, grid: Grid | None) -> jax.Array:
    """``K_n delta^2 / 2 + K_t |xi|^2 / 2`` over particle-particle and wall contacts (J) for
    the current positions and springs (a zero-length step keeps the springs as they are)."""
    p = state.particles
    prm = replace(params, dt=jnp.zeros_like(params.dt))
    contacts = state.contacts
    if grid is not None:  # a fresh pair list, e.g. after a host-side replacement
        contacts, _ = build_pairs(p, contacts, params.skin, grid)
    _, _, _, pinfo = pair_forces(p, contacts, prm)
    cap = 2 * contacts.capacity
    _, _, _, _, winfo = wall_forces(p, state.walls, contacts.wall_xi, prm, capacity=cap)
    return pinfo["energy"]["elastic"] + winfo["energy"]["elastic"]


@eqx.filter_jit
def _stored(state: SimState, params: Params, grid: Grid | None = None) -> dict:
    out = {
        "kinetic": kinetic_energy(state),
        "contact": _contact_elastic(state, params, grid),
        "bond": jnp.zeros((), state.particles.pos.dtype),
    }
    if isinstance(state.bonds, Bonds):
        b = bond_energy(state.particles, state.bonds)
        out["bond"] = b + wall_bond_energy(state.particles, state.bonds, state.walls)
    return out


def stored_energy(state: SimState, params: Params, grid: Grid | None = None) -> dict:
    """Kinetic, contact elastic and bond elastic energy of ``state`` (J, floats) and their
    sum ``total``. ``grid``: rebuild the pair list first (needed when the state's list is
    stale, e.g. right after particles were replaced on the host)."""
    out = {k: float(v) for k, v in _stored(state, params, grid).items()}
    out["total"] = out["kinetic"] + out["contact"] + out["bond"]
    return out


def attach(state: SimState, params: Params, grid: Grid | None = None) -> SimState:
    """``state`` with a zeroed :class:`~jaxgran.state.EnergyLedger` whose ``stored0`` is the
    stored energy now. The pair list must be current (after :func:`jaxgran.simulate.prepare`
    or a segment), or pass ``grid`` to build one for the stored energy. Raises ``TypeError``
    for a bond model the ledger cannot account for."""
    if state.bonds is not None and not isinstance(state.bonds, Bonds):
        raise TypeError(
            f"the energy ledger supports the paper-002 bonds (jaxgran.bonds.Bonds), not "
            f"{type(state.bonds).__name__}: its dashpots and damage are not accounted"
        )
    fd = state.particles.pos.dtype
    zero = jnp.zeros((), fd)
    stored0 = jnp.asarray(stored_energy(state, params, grid)["total"], fd)
    ledger = EnergyLedger(
        boundary_work=zero,
        body_work=zero,
        dashpot=zero,
        friction=zero,
        damping=zero,
        breakage=zero,
        stored0=stored0,
    )
    return replace(state, energy=ledger)


def control_terms(ledger: EnergyLedger, ke_before, ke_damped, ke_after) -> EnergyLedger:
    """Book a control's velocity update: ``ke_before - ke_damped`` is removed by background
    damping, ``ke_after - ke_damped`` is the work of the applied body forces (J)."""
    return replace(
        ledger,
        damping=ledger.damping + (ke_before - ke_damped),
        body_work=ledger.body_work + (ke_after - ke_damped),
    )


def account_host_change(
    before: SimState, after: SimState, params: Params, grid: Grid | None = None
) -> SimState:
    """``after`` with ``stored(before) - stored(after)`` added to its ledger's breakage
    term: the energy a host-side change (particle replacement, fragment erosion, fines
    removed) takes out of the system. ``params`` are those the contact law uses; ``grid``
    rebuilds ``after``'s pair list first if it is stale. No-op without a ledger."""
    if after.energy is None:
        return after
    e0 = stored_energy(before, params)["total"]
    e1 = stored_energy(after, params, grid)["total"]
    led = after.energy
    fd = led.breakage.dtype
    return replace(after, energy=replace(led, breakage=led.breakage + jnp.asarray(e0 - e1, fd)))


def balance(state: SimState, params: Params) -> dict:
    """The energy balance since :func:`attach` (J, floats).

    Returns the ledger's terms, the stored energies (``kinetic``, ``contact``, ``bond``),
    ``input = boundary_work + body_work``, ``stored_change``, ``dissipated`` (dashpot +
    friction + damping + breakage), ``residual = input - stored_change - dissipated`` and
    ``relative_error = |residual| / |input|`` (NaN when nothing was put in).
    """
    if state.energy is None:
        raise ValueError("no energy ledger on this state: use jaxgran.energy.attach first")
    led = {f.name: float(getattr(state.energy, f.name)) for f in dataclasses.fields(state.energy)}
    st = stored_energy(state, params)
    inp = led["boundary_work"] + led["body_work"]
    change = st["total"] - led["stored0"]
    diss = led["dashpot"] + led["friction"] + led["damping"] + led["breakage"]
    resid = inp - change - diss
    out = dict(led)
    out.update({k: st[k] for k in ("kinetic", "contact", "bond")})
    out.update(
        {
            "input": inp,
            "stored_change": change,
            "dissipated": diss,
            "residual": resid,
            "relative_error": abs(resid) / abs(inp) if inp != 0 else float(np.nan),
        }
    )
    return out
