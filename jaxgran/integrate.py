"""Time integration: one DEM step as a pure function, and the time-step limit.

Velocity Verlet (kick-drift-kick) for translation and the same half-step scheme for rotation
(equivalent to the leap-frog of paper 002 §2.1 with velocities known at whole steps).
The tangential spring increments and the bonds' dashpots use the half-step velocities; the
contact dashpots use the end-of-step velocity predicted with the previous force (second-order
dissipation), which bounds the step together with the springs (:func:`critical_time_step`;
:func:`linear_step_radius` checks a packing). The scheme is second order, and for contact
forces that balance torque it conserves linear and angular momentum to round-off.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .contact import pair_forces, wall_forces
from .partition import build_pairs, needs_rebuild
from .state import (
    ERR_CONTACT_OVERFLOW,
    ERR_NAN,
    ERR_PAIR_OVERFLOW,
    ERR_SKIN_EXCEEDED,
    WALL_SERVO,
    WALL_VELOCITY,
    Grid,
    Params,
    Particles,
    SimState,
    Walls,
    replace,
)


def mode_time_step_limit(omega2: float, gamma: float) -> float:
    """Largest stable step (s) of :func:`step` for one mode ``x'' + gamma x' + omega2 x = 0``
    (``omega2`` in 1/s^2, ``gamma`` in 1/s): the root of ``(Omega dt / 2)^2 + gamma dt = 1``,
    ``2 / (gamma + sqrt(gamma^2 + omega2))`` (docs/stability.md)."""
    return float(2.0 / (gamma + np.sqrt(gamma**2 + omega2)))


def contact_dashpot_rate(particles: Particles, damping: float) -> float:
    """Largest rate (1/s) at which one contact's dashpot ``G m_e`` (``G = damping``, 1/s)
    damps the velocity of its contact point among the active particles: ``G (1 +
    lambda_max)`` with ``lambda = m l^2 / I`` (l = bounding radius; see
    :func:`critical_time_step`)."""
    act = np.asarray(particles.active)
    lam = np.asarray(particles.mass) * np.asarray(particles.bound_radius) ** 2
    lam = lam[act] / np.asarray(particles.inertia)[act]
    return float(damping) * (1.0 + float(np.max(lam)))


def critical_time_step(particles: Particles, params: Params, dashpots: bool = True) -> float:
    """Stability limit of the explicit scheme (s) for one contact between two bodies, with
    its spring and its dashpots.

    Spring: a pair of equal bodies on a spring K_n oscillates at ``Omega^2 = 2 K_n / m``;
    rotation adds an effective mass ``I / l^2`` (l = bounding radius), so ``Omega^2 = 2 K_n /
    m_min`` with ``m_min = min(m, I/l^2)`` over active particles.

    Dashpots: a contact's dashpot ``G m_e`` (``G = max(G_n, G_t)``, 1/s) damps the relative
    velocity of its contact point at the rate ``Gamma = G m_e (1/m_i + l_i^2/I_i + 1/m_j +
    l_j^2/I_j)``; since ``m_e (1/m_i + 1/m_j) = 1`` this is at most ``G (1 + lambda_max)``
    with ``lambda = m l^2 / I`` (a wall contact, ``m_e = m``, gives the same bound). The
    rotation term makes it several times ``G``: 2.6 for a regular pentagon, up to ~5 for
    Voronoi cells.

    :func:`step` feeds the dashpots the end-of-step velocity predicted with the previous
    force, which keeps the booked dissipation second order in dt; for one mode
    ``x'' + Gamma x' + Omega^2 x = 0`` that scheme is stable for ``(Omega dt / 2)^2 + Gamma dt
    <= 1`` (docs/stability.md), hence ``dt_crit = 2 / (Gamma + sqrt(Gamma^2 + Omega^2))``:
    ``2 / Omega`` without dashpots (Verlet, PHYSICS §D), ``1 / Gamma`` for a pure damper.
    Several contacts stiffen and damp a particle more (the springs' ``Omega^2`` and the
    dashpots' ``Gamma`` both add up over its contacts), which is why :func:`stable_time_step`
    takes a safety factor well below 1. ``dashpots=False`` gives the springs' limit alone
    ``sqrt(2 m_min / K_n)`` (the rule before 2026-12-05, for comparisons).
    """
    act = np.asarray(particles.active)
    if not act.any():
        raise ValueError("no active particle: cannot choose a time step")
    m = np.asarray(particles.mass)[act]
    inertia = np.asarray(particles.inertia)[act]
    ell = np.asarray(particles.bound_radius)[act]
    m_rot = np.minimum(m, inertia / ell**2)
    k = float(params.normal_stiffness)
    omega2 = 2.0 * k / float(m_rot.min())
    damping = max(float(params.normal_damping), float(params.tangential_damping), 0.0)
    gamma = contact_dashpot_rate(particles, damping) if dashpots else 0.0
    return mode_time_step_limit(omega2, gamma)


def stable_time_step(particles: Particles, params: Params, safety: float = 0.15) -> float:
    """Recommended time step (s): ``safety * critical_time_step``."""
    if not 0 < safety <= 1:
        raise ValueError(f"safety factor must be in (0, 1], got {safety}")
    return safety * critical_time_step(particles, params)


def check_time_step(particles: Particles, params: Params) -> None:
    """Raise ValueError if ``params.dt`` exceeds the stability limit."""
    dt = float(params.dt)
    crit = critical_time_step(particles, params)
    if dt > crit:
        raise ValueError(
            f"time step dt={dt:.3e} s exceeds the stability limit {crit:.3e} s of the stiffest "
            f"contact (K_n={float(params.normal_stiffness):.3e} N/m, dashpots G_n="
            f"{float(params.normal_damping):.3e} and G_t={float(params.tangential_damping):.3e}"
            f" 1/s); use dt <= {0.15 * crit:.3e} s (jaxgran.integrate.stable_time_step), or "
            "lower K_n or the damping"
        )


def wall_velocity(walls: Walls, thickness: Array, dt: Array | float = 0.0) -> tuple[Array, Array]:
    """Velocity of every wall for the coming step (m/s), and the servo's new integral term.

    Servo walls move along their normal so that the compressive stress the particles exert,
    ``-F . n / (length * thickness)``, approaches ``target_stress``. With the error
    ``e = target - stress`` the speed is ``v = g e + I``, capped at ``max_speed``, where the
    integral term ``I`` (``servo_integral``, m/s) grows by ``g e dt / T_i`` per step
    (``T_i = servo_time``; +inf keeps ``I = 0``, the proportional servo) and is itself
    capped at ``max_speed`` (no wind-up). With ``T_i`` of about four times the loop's time
    constant ``1 / (g K / (L t))`` the loop is critically damped, and a specimen that dilates
    at a steady rate is held at the target stress instead of ``rate / g`` away from it.

    Returns:
        ``(velocity [W, 2], servo_integral [W])``.
    """
    stress = -jnp.sum(walls.force * walls.normal, axis=-1) / (walls.length * thickness)
    err = walls.target_stress - stress
    servo_on = walls.mode == WALL_SERVO
    finite = jnp.isfinite(walls.servo_time)
    rate = jnp.where(finite, 1.0 / jnp.where(finite, walls.servo_time, 1.0), 0.0)
    integral = walls.servo_integral + walls.servo_gain * err * rate * dt
    integral = jnp.where(servo_on, jnp.clip(integral, -walls.max_speed, walls.max_speed), 0.0)
    speed = jnp.clip(walls.servo_gain * err + integral, -walls.max_speed, walls.max_speed)
    servo = speed[:, None] * walls.normal
    moving = walls.mode == WALL_VELOCITY
    v = jnp.where(moving[:, None], walls.vel, 0.0)
    return jnp.where(servo_on[:, None], servo, v), integral


def servo_gain_for(length: float, thickness: float, stiffness: float, response_time: float):
    """Servo gain (m/(s Pa)) that makes a wall pressing on contacts of total stiffness
    ``stiffness`` (N/m) reach its target stress with time constant ``response_time`` (s):
    ``d sigma/dt = -(K gain / (L t)) (sigma - target)``, so ``gain = L t / (K tau)``. Keep
    ``tau`` well above the contact period (several hundred steps) or the loop oscillates."""
    if min(length, thickness, stiffness, response_time) <= 0:
        raise ValueError("length, thickness, stiffness and response_time must be positive")
    return length * thickness / (stiffness * response_time)


def step(
    state: SimState, params: Params, grid: Grid, rebuild: Array | None = None
) -> tuple[SimState, Array]:
    """Advance one time step. Returns the new state and the error bits of this step.

    ``rebuild`` (scalar bool, optional) overrides the pair-list rebuild decision (by default
    :func:`jaxgran.partition.needs_rebuild` after the drift). Under ``vmap`` pass one flag
    for the whole batch (``any`` over the realisations, :mod:`jaxgran.ensemble`): an
    unbatched predicate keeps the ``lax.cond`` a branch instead of a ``select`` that would
    rebuild every step. Rebuilding when not needed changes nothing but round-off."""
    p = state.particles
    dt = params.dt
    free = p.active & ~p.fixed
    inv_m = jnp.where(free, 1.0 / p.mass, 0.0)
    inv_i = jnp.where(free, 1.0 / p.inertia, 0.0)

    # kick (half) + drift
    vel = p.vel + 0.5 * dt * p.force * inv_m[:, None]
    omega = p.omega + 0.5 * dt * p.torque * inv_i
    pos = jnp.where(p.active[:, None], p.pos + dt * vel, p.pos)
    angle = jnp.where(p.active, p.angle + dt * omega, p.angle)
    errors = jnp.where(
        jnp.any(p.active & (jnp.linalg.norm(dt * vel, axis=-1) > 0.5 * params.skin)),
        ERR_SKIN_EXCEEDED,
        0,
    ).astype(jnp.int32)
    p = replace(p, pos=pos, angle=angle, vel=vel, omega=omega)

    walls = state.walls
    wvel, integral = wall_velocity(walls, params.thickness, dt)
    walls = replace(walls, point=walls.point + dt * wvel, vel=wvel, servo_integral=integral)

    if rebuild is None:
        rebuild = needs_rebuild(p, state.contacts, params.skin)
    contacts, build_err = jax.lax.cond(
        rebuild,
        lambda c: build_pairs(p, c, params.skin, grid),
        lambda c: (c, jnp.zeros((), jnp.int32)),
        state.contacts,
    )
    errors = errors | build_err

    # dashpots see the end-of-step velocity predicted with the old force (second order)
    damp = (vel + 0.5 * dt * p.force * inv_m[:, None], omega + 0.5 * dt * p.torque * inv_i)
    f_pp, t_pp, xi, pinfo = pair_forces(p, contacts, params, damp)
    errors = errors | _contact_overflow(pinfo)
    f_w, t_w, wall_xi, on_wall, winfo = wall_forces(
        p, walls, contacts.wall_xi, params, damp, capacity=2 * contacts.capacity
    )
    errors = errors | _contact_overflow(winfo)
    gravity = jnp.where(p.active[:, None], p.mass[:, None] * params.gravity[None, :], 0.0)
    force = f_pp + f_w + gravity
    torque = t_pp + t_w
    bonds = state.bonds
    if bonds is not None:  # static: a scene with bonds compiles its own step
        from .bonds import bond_forces, force_on_walls

        f_b, t_b, bonds = bond_forces(p, bonds, walls, dt)
        force = force + f_b
        torque = torque + t_b
        on_wall = on_wall + force_on_walls(bonds, walls.point.shape[0])
    ledger = state.energy
    if ledger is not None:  # static, like the bonds
        ledger = _ledger_step(ledger, state, p, bonds, on_wall, wvel, gravity, pinfo, winfo, dt)

    # kick (half)
    vel = vel + 0.5 * dt * force * inv_m[:, None]
    omega = omega + 0.5 * dt * torque * inv_i
    p = replace(p, vel=vel, omega=omega, force=force, torque=torque)
    contacts = replace(contacts, xi=xi, wall_xi=wall_xi)
    walls = replace(walls, force=on_wall)
    finite = jnp.all(jnp.isfinite(p.pos)) & jnp.all(jnp.isfinite(p.vel))
    finite = finite & jnp.all(jnp.isfinite(p.omega)) & jnp.all(jnp.isfinite(p.angle))
    errors = errors | jnp.where(finite, 0, ERR_NAN)
    new = SimState(
        particles=p,
        walls=walls,
        contacts=contacts,
        time=state.time + dt,
        step=state.step + 1,
        bonds=bonds,
        energy=ledger,
    )
    return new, errors.astype(jnp.int32)


def _ledger_step(
    ledger, old: SimState, p: Particles, bonds, on_wall, wvel, gravity, pinfo, winfo, dt
):
    """The energy ledger after one step (:class:`jaxgran.state.EnergyLedger`).

    Wall work is the trapezoid of the force the walls exert on the particles over the
    wall's displacement ``v_w dt``; gravity's work is ``m g . dx`` (exact for a constant
    force); the contact terms are the sums of :func:`jaxgran.contact.contact_law`'s; the
    breakage term is the bond energy this step's health update removes, evaluated at the
    mid-step positions: the update happens at the end of the drift, so the force the
    trapezoid sees drops at the end point, and booking the loss there would leave a
    first-order error (``k delta v dt / 2`` for a bond breaking at opening ``delta``); at
    the midpoint the balance stays second order."""
    from .bonds import Bonds, bond_energy

    w_wall = -0.5 * jnp.sum((old.walls.force + on_wall) * wvel) * dt
    moved = p.pos - old.particles.pos
    free = (p.active & ~p.fixed)[:, None]
    w_body = jnp.sum(jnp.where(free, gravity * moved, 0.0))
    dashpot = pinfo["energy"]["dashpot"] + winfo["energy"]["dashpot"]
    slip = pinfo["energy"]["slip"] + winfo["energy"]["slip"]
    released = jnp.zeros((), ledger.breakage.dtype)
    if isinstance(bonds, Bonds):
        q = old.particles
        mid = replace(p, pos=0.5 * (q.pos + p.pos), angle=0.5 * (q.angle + p.angle))
        released = bond_energy(mid, old.bonds) - bond_energy(mid, bonds)
    return replace(
        ledger,
        boundary_work=ledger.boundary_work + w_wall,
        body_work=ledger.body_work + w_body,
        dashpot=ledger.dashpot + dashpot,
        friction=ledger.friction + slip,
        breakage=ledger.breakage + released,
    )


def _contact_overflow(info) -> Array:
    """Error bits of a full compacted contact list (grown with the pair capacity)."""
    return jnp.where(info["overflow"], ERR_CONTACT_OVERFLOW | ERR_PAIR_OVERFLOW, 0).astype(
        jnp.int32
    )


def initial_forces(state: SimState, params: Params, grid: Grid) -> tuple[SimState, Array]:
    """Build the pair list and evaluate forces for the current positions (no motion), so
    the first Verlet kick uses consistent forces."""
    p = state.particles
    contacts, errors = build_pairs(p, state.contacts, params.skin, grid)
    f_pp, t_pp, xi, pinfo = pair_forces(p, contacts, params)
    errors = errors | _contact_overflow(pinfo)
    f_w, t_w, wall_xi, on_wall, winfo = wall_forces(
        p, state.walls, contacts.wall_xi, params, capacity=2 * contacts.capacity
    )
    errors = errors | _contact_overflow(winfo)
    gravity = jnp.where(p.active[:, None], p.mass[:, None] * params.gravity[None, :], 0.0)
    # springs start from zero: the evaluation above only primes them with v_t dt
    del xi, wall_xi
    force, torque = f_pp + f_w + gravity, t_pp + t_w
    if state.bonds is not None:
        from .bonds import bond_forces, force_on_walls

        f_b, t_b, bonds = bond_forces(p, state.bonds, state.walls, 0.0)
        force, torque = force + f_b, torque + t_b
        on_wall = on_wall + force_on_walls(bonds, state.walls.point.shape[0])
    p = replace(p, force=force, torque=torque)
    return (
        SimState(
            particles=p,
            walls=replace(state.walls, force=on_wall),
            contacts=contacts,
            time=state.time,
            step=state.step,
            bonds=state.bonds,
            energy=state.energy,
        ),
        errors,
    )


def _contact_forces(state: SimState, params: Params, pos, angle, vel, omega, dvel, domega):
    """Contact forces ``[n, 2]`` and torques ``[n]`` of ``state``'s contact list at the
    given positions, angles, half-step velocities, spins and dashpot velocities, spins."""
    p, c, w = state.particles, state.contacts, state.walls
    q = replace(p, pos=pos, angle=angle, vel=vel, omega=omega)
    f, t, _, _ = pair_forces(q, c, params, (dvel, domega))
    fw, tw, _, _, _ = wall_forces(q, w, c.wall_xi, params, (dvel, domega), 2 * c.capacity)
    return f + fw, t + tw


def _bond_forces(state: SimState, params: Params, pos, angle, vel, omega):
    """Bond forces ``[n, 2]`` and torques ``[n]`` at the given positions and velocities."""
    from .bonds import bond_forces

    q = replace(state.particles, pos=pos, angle=angle, vel=vel, omega=omega)
    f, t, _ = bond_forces(q, state.bonds, state.walls, 0.0)
    return f, t


def _jacobian(state: SimState, params: Params, bonds: bool) -> np.ndarray:
    """``[3n, 9n]`` (contacts) or ``[3n, 6n]`` (bonds): rows the forces and torques
    ``(f_x0, f_y0, ..., t_0, ...)``, columns ``(x, y, angle)`` of each argument of
    ``(pos, angle, vel, omega, damping vel, damping omega)`` in turn.

    Column by column, each a ``jax.jvp`` along a unit direction, jitted with the state and
    parameters as constants. The jitted ``jax.jacfwd``/``jacrev`` of the force evaluation,
    and a jitted ``jvp`` taking the state as an input, hit an LLVM instruction-selection
    error on the x86 CPU backend for some packings (jax 0.10: "Cannot select
    X86ISD::SUBV_BROADCAST_LOAD" in a ``concatenate_bitcast_fusion``; the process aborts);
    this graph compiles (once per call)."""
    p = state.particles
    n = p.pos.shape[0]
    args = (p.pos, p.angle, p.vel, p.omega, p.vel, p.omega)[: 4 if bonds else 6]
    law = _bond_forces if bonds else _contact_forces

    width = 3 * n * (len(args) // 2)

    @jax.jit
    def column(c):
        e = jnp.zeros(width, p.pos.dtype).at[c].set(1.0)
        tangent = []
        for k in range(len(args) // 2):
            block = e[3 * n * k : 3 * n * (k + 1)]
            tangent += [block[: 2 * n].reshape(n, 2), block[2 * n :]]
        df, dtq = jax.jvp(lambda *a: law(state, params, *a), args, tuple(tangent))[1]
        return df.reshape(-1), dtq

    cols = []
    for c in range(width):
        df, dtq = column(c)
        cols.append(np.concatenate([np.asarray(df), np.asarray(dtq)]))
    return np.stack(cols, axis=1)


def linear_step_radius(state: SimState, params: Params, dt: float | None = None) -> dict:
    """Spectral radius of one :func:`step`, linearised about ``state`` with its contacts
    (and bonds).

    The forces are differentiated (one ``jax.jvp`` per column, assembled on the host: a
    diagnostic, not a hot path) with respect to the positions and angles (stiffness), the
    half-step velocity (the contacts' tangential spring increment ``v_t dt``, which acts as
    a stiffness on the displacement; the bonds' dashpots, e.g. the interface elements') and
    the velocity the contact dashpots see (predicted end of step). Mass-normalised over the
    free particles' ``(x, y, angle)`` they give the stiffness ``A`` and the dampings ``B``
    (contact dashpots) and ``D`` (bond dashpots), and the step, on the state ``(x, v, a)``,
    is the linear map

        ``v_h = v + dt a / 2``, ``x' = x + dt v_h``,
        ``a' = -A x' - B (v + dt a) - D v_h``, ``v' = v_h + dt a' / 2``.

    A radius above 1 by more than the geometric (rolling) modes' ``1 + O(dt)`` means the
    scheme amplifies a perturbation of this packing at every step. Friction caps, the
    no-tension clamp and bond damage are taken in the state they are in (a linearisation).

    Args:
        state: a state whose contact list and tangential springs are current (after a
            :func:`jaxgran.simulate.simulate` or :func:`initial_forces`).
        dt: time step (s); default ``params.dt``.

    Returns:
        dict: ``radius`` and ``radius_without_dashpots`` (the same step with ``B = D = 0``),
        ``omega2`` (the largest real part of an eigenvalue of ``A``, 1/s^2), ``gamma``
        (the largest eigenvalue of ``B + D / 2``, 1/s) and ``criterion`` ``(sqrt(omega2) dt
        / 2)^2 + gamma dt``: one mode at a time, the step is stable for <= 1
        (:func:`critical_time_step`). The dense eigenproblem has ``9 n`` rows for ``n`` free
        particles: keep ``n`` to a few hundred.
    """
    p = state.particles
    dt = float(params.dt) if dt is None else float(dt)
    n = p.pos.shape[0]
    j_contact = _jacobian(state, params, bonds=False)
    j_bond = np.zeros((3 * n, 6 * n)) if state.bonds is None else _jacobian(state, params, True)
    cols = lambda k: slice(3 * n * k, 3 * n * (k + 1))  # noqa: E731  x, v_h, v_d blocks
    stiffness = -j_contact[:, cols(0)] - j_contact[:, cols(1)] / float(params.dt)
    damping = -j_contact[:, cols(2)]
    stiffness = stiffness - j_bond[:, cols(0)]
    half_damping = -j_bond[:, cols(1)]
    free = np.asarray(p.active & ~p.fixed)
    keep = np.concatenate([np.repeat(free, 2), free])
    mass = np.concatenate([np.repeat(np.asarray(p.mass), 2), np.asarray(p.inertia)])
    inv_m = np.divide(1.0, mass, out=np.zeros_like(mass), where=keep)  # padding: no mass

    def normalised(mat: np.ndarray) -> np.ndarray:
        return (inv_m[:, None] * mat)[np.ix_(keep, keep)]

    a_mat, b_mat, d_mat = normalised(stiffness), normalised(damping), normalised(half_damping)

    def radius(b: np.ndarray, d: np.ndarray) -> float:
        e = np.eye(a_mat.shape[0])
        x1 = [e, dt * e, 0.5 * dt * dt * e]  # columns: x, v, a
        vh = [0.0 * e, e, 0.5 * dt * e]
        a1 = [-a_mat @ x1[0], -a_mat @ x1[1] - b - d, -a_mat @ x1[2] - dt * b - 0.5 * dt * d]
        v1 = [vh[k] + 0.5 * dt * a1[k] for k in range(3)]
        return float(np.max(np.abs(np.linalg.eigvals(np.block([x1, v1, a1])))))

    omega2 = float(np.max(np.linalg.eigvals(a_mat).real))
    gamma = float(np.max(np.linalg.eigvals(b_mat + 0.5 * d_mat).real))
    zero = np.zeros_like(b_mat)
    return {
        "radius": radius(b_mat, d_mat),
        "radius_without_dashpots": radius(zero, zero),
        "omega2": omega2,
        "gamma": gamma,
        "criterion": (np.sqrt(max(omega2, 0.0)) * dt / 2) ** 2 + gamma * dt,
    }
