"""iLQG on true MuJoCo C (gnwarp.control.ilqg) against an independent finite-horizon LQR."""
import mujoco
import numpy as np
import pytest

from gnwarp import sim
from gnwarp.control.ilqg import ILQG, ILQGSettings, BodyPointCost, QuadraticCost, body_state_cost, task_cost
from gnwarp.control.tasks import get_task

# two coupled sliders, a spring and damping, no gravity or contacts, Euler: linear dynamics
_LINEAR = """<mujoco><option timestep="0.05" gravity="0 0 0" integrator="Euler"><flag contact="disable"/></option>
<worldbody><body name="a"><joint name="j1" type="slide" axis="1 0 0" stiffness="1" damping="0.2"/>
<geom type="sphere" size="0.1" mass="1"/>
<body name="b"><joint name="j2" type="slide" axis="1 0 0"/><geom type="sphere" size="0.1" mass="0.5"/></body></body>
</worldbody><actuator><motor joint="j1" {lim}/><motor joint="j2" gear="2" {lim}/></actuator></mujoco>"""
H = 30
Q, R, QF = np.diag([1.0, 2.0, 0.1, 0.1]), 0.01 * np.eye(2), 10 * np.eye(4)
X0 = np.array([1.0, -0.5, 0.3, 0.0])


def _linear_model(lim: str = "") -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(_LINEAR.format(lim=lim))


def _lqr(m: mujoco.MjModel, substeps: int = 1):
    """Time-varying gains of the finite-horizon LQR, by a Riccati recursion on the knot A, B."""
    A1, B1 = np.zeros((4, 4)), np.zeros((4, 2))
    mujoco.mjd_transitionFD(m, mujoco.MjData(m), 1e-6, True, A1, B1, None, None)
    A, B = np.eye(4), np.zeros((4, 2))
    for _ in range(substeps):
        A, B = A1 @ A, A1 @ B + B1
    P, gains = QF, []
    for _ in range(H):
        K = -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        P = Q + A.T @ P @ A + A.T @ P @ B @ K
        gains.append(K)
    return A, B, gains[::-1]


def _lqr_controls(A, B, gains, clamp=None, m=None, substeps=1):
    """LQR controls along the trajectory from X0: linear model, or (clamp) the true one, clamped."""
    x, U = X0.copy(), []
    d = None if m is None else mujoco.MjData(m)
    if d is not None:
        d.qpos[:], d.qvel[:] = X0[:2], X0[2:]
    for K in gains:
        u = K @ (x if d is None else np.r_[d.qpos, d.qvel])
        if clamp is not None:
            u = np.clip(u, -clamp, clamp)
        U.append(u)
        if d is None:
            x = A @ x + B @ u
        else:
            d.ctrl[:] = u
            mujoco.mj_step(m, d, substeps)
    return np.array(U)


@pytest.mark.parametrize("substeps", [1, 2])
def test_unconstrained_reaches_lqr(substeps):
    m = _linear_model()
    A, B, gains = _lqr(m, substeps)
    U_lqr = _lqr_controls(A, B, gains)
    il = ILQG(m, QuadraticCost(m, Q, R), QuadraticCost(m, QF),
              ILQGSettings(horizon=H, substeps=substeps, iterations=5, nthread=2))
    U, info = il.plan(X0[:2], X0[2:])
    np.testing.assert_allclose(U, U_lqr, atol=1e-5 * np.abs(U_lqr).max())
    assert info["cost"] == pytest.approx(il.total_cost(X0[:2], X0[2:], U_lqr), rel=1e-8)
    # a generic cost (no analytic derivatives): finite-difference cost derivatives, same answer
    fd = ILQG(m, lambda d, u: QuadraticCost(m, Q, R)(d, u), lambda d: QuadraticCost(m, QF)(d),
              ILQGSettings(horizon=H, substeps=substeps, iterations=5, nthread=1))
    U_fd, _ = fd.plan(X0[:2], X0[2:])
    np.testing.assert_allclose(U_fd, U_lqr, atol=1e-4 * np.abs(U_lqr).max())


def test_box_respected_and_beats_clamped_lqr():
    bound = 0.5
    m = _linear_model(f'ctrllimited="true" ctrlrange="-{bound} {bound}"')
    A, B, gains = _lqr(m)
    il = ILQG(m, QuadraticCost(m, Q, R), QuadraticCost(m, QF), ILQGSettings(horizon=H, iterations=30))
    U, info = il.plan(X0[:2], X0[2:])
    assert np.all(np.abs(U) <= bound + 1e-12) and np.isclose(np.abs(U).max(), bound)
    clamped_closed = il.total_cost(X0[:2], X0[2:], _lqr_controls(A, B, gains, bound, m))
    clamped_open = il.total_cost(X0[:2], X0[2:], np.clip(_lqr_controls(A, B, gains), -bound, bound))
    assert info["cost"] < 0.95 * min(clamped_closed, clamped_open)
    # the problem is a convex QP: projected gradient on the open-loop controls cannot improve it
    S = np.zeros((H, 4, H, 2))  # S[t]: x_{t+1} as a linear map of U (plus A^{t+1} x_0)
    x_free = [X0]
    for t in range(H):
        if t:
            S[t] = np.einsum("ik,kuj->iuj", A, S[t - 1])
        S[t, :, t] = B
        x_free.append(A @ x_free[-1])
    x = np.einsum("tiuj,uj->ti", S, U) + np.array(x_free[1:])
    grad = U @ R + np.einsum("tiuj,ti->uj", S[:-1], x[:-1] @ Q) + np.einsum("iuj,i->uj", S[-1], QF @ x[-1])
    step = np.clip(U - 1e-2 * grad, -bound, bound) - U
    assert np.abs(step).max() < 1e-4


def _pendulum_cost(m):
    def reward(body, u):  # pole's z axis . up, the balance reward, and a small control cost
        q = body[1, 3:7]
        return 1 - 2 * (q[1] ** 2 + q[2] ** 2) - 0.01 * u @ u
    return body_state_cost(m, reward)


def test_line_search_never_increases_cost():
    s = sim.make("pendulum")
    # steps from 4 down: the long ones overshoot and must be refused
    il = ILQG.for_system(s, _pendulum_cost(s.model), settings=ILQGSettings(
        horizon=50, iterations=15, nthread=2, step_sizes=(4.0, 2.0, 1.0, 0.5, 0.25, 0.1)))
    u0 = np.random.default_rng(0).uniform(-1, 1, (50, 1))
    U, info = il.plan(np.array([1.0]), np.zeros(1), u_init=u0)
    costs = np.array(info["costs"])
    assert np.all(np.diff(costs) <= 0) and costs[-1] < costs[0] - 1
    assert min(info["alphas"]) < 4.0
    assert info["cost"] == pytest.approx(il.total_cost(np.array([1.0]), np.zeros(1), U))
    assert np.all(np.abs(U) <= 1)
    # linear-quadratic: the Newton step is alpha = 1, and alpha >= 2 cannot lower the cost, so
    # every step is refused, the cost stays and the regularization grows
    m = _linear_model()
    il = ILQG(m, QuadraticCost(m, Q, R), QuadraticCost(m, QF),
              ILQGSettings(horizon=H, iterations=3, step_sizes=(8.0, 4.0, 3.0)))
    _, info = il.plan(X0[:2], X0[2:])
    assert info["alphas"] == [0.0] * 3 and len(set(info["costs"])) == 1
    assert np.all(np.diff([1e-6] + info["reg"]) > 0)


def test_regularization_grows_when_backward_pass_fails():
    s = sim.make("pendulum")
    # a negative control weight makes Quu indefinite until the regularization outweighs it
    il = ILQG.for_system(s, QuadraticCost(s.model, np.eye(2), -np.eye(1)), settings=ILQGSettings(
        horizon=10, iterations=3, reg_init=1e-6, reg_min=1e-6, reg_factor=10.0))
    _, info = il.plan(np.array([0.1]), np.zeros(1))
    assert info["backward_failures"] >= 6 and max(info["reg"]) >= 1.0
    assert np.all(np.diff(info["costs"]) <= 0)


def test_receding_horizon_warm_start_and_errors():
    m = _linear_model()
    il = ILQG(m, QuadraticCost(m, Q, R), QuadraticCost(m, QF), ILQGSettings(horizon=H, iterations=2))
    U1, _ = il.plan(X0[:2], X0[2:])
    il.iterations = 0  # no iterations: the plan is the warm start itself
    U2, info = il.plan(X0[:2], X0[2:])
    np.testing.assert_array_equal(U2, np.concatenate([U1[1:], U1[-1:]]))
    assert info["costs"] == [info["cost"]]
    il.reset()
    np.testing.assert_array_equal(il.plan(X0[:2], X0[2:])[0], 0)
    with pytest.raises(ValueError, match="NaN"):
        il.plan(np.array([np.nan, 0.0]), X0[2:])
    with pytest.raises(ValueError, match="horizon"):
        ILQG(m, QuadraticCost(m, Q, R), settings=ILQGSettings(horizon=0))


def test_pendulum_closed_loop_balance():
    s = sim.make("pendulum")
    m = s.model
    il = ILQG.for_system(s, _pendulum_cost(m), settings=ILQGSettings(horizon=25, iterations=3))
    d, passive = mujoco.MjData(m), mujoco.MjData(m)
    d.qpos[0] = passive.qpos[0] = 0.15  # gravity's torque here is ~0.75 of the torque limit
    upright = []
    for _ in range(50):  # 1 s, replanning every data step on the true state
        d.ctrl[:] = il.action(d.qpos, d.qvel)
        mujoco.mj_step(m, d, s.substeps)
        mujoco.mj_step(m, passive, s.substeps)
        upright.append(np.cos(d.qpos[0]))
    assert min(upright) > 0.98 and abs(d.qpos[0]) < 0.05
    assert np.cos(passive.qpos[0]) < 0.5  # without control it falls


def test_task_cost_wraps_a_task_reward():
    s = sim.make("pendulum")
    cost = task_cost(s.model, get_task("pendulum-balance"))
    d = mujoco.MjData(s.model)
    d.qpos[0] = -0.3
    mujoco.mj_forward(s.model, d)
    assert cost(d, np.zeros(1)) == pytest.approx(0.3)  # minus the reward: the angle from upright
    with pytest.raises(ValueError, match="displacements"):
        task_cost(sim.make("swimmer6").model, get_task("swimmer-reach"))


def _random_state(m, seed: int, spread: float):
    """MjData at a random state of ``m`` (qpos spread around qpos0, unit-normal qvel), after
    mj_forward; and the generator, for more draws."""
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    d.qpos[:] = m.qpos0 + spread * rng.standard_normal(m.nq)
    d.qvel[:] = rng.standard_normal(m.nv)
    mujoco.mj_forward(m, d)
    return d, rng


def test_body_point_cost_derivatives_match_finite_differences():
    """BodyPointCost's analytic lx equals the generic finite-difference gradient; where the point
    sits on its reference the Gauss-Newton lxx is the exact Hessian, so it matches FD too."""
    m = sim.make("swimmer6").model
    d, rng = _random_state(m, 3, 0.3)
    W = np.diag([0.7, 0.2, 0.0])
    il = ILQG(m, lambda dd, u: 0.0, settings=ILQGSettings(horizon=2, nthread=1))
    for ref, lin in [(d.xpos[1] + [0.1, -0.2, 0.0], np.array([-0.6, 0.8, 0.0])), (d.xpos[1].copy(), None)]:
        cost = BodyPointCost(m, 1, ref, lin=lin, W=W, R=0.1 * np.eye(m.nu))
        u = rng.standard_normal(m.nu)
        fd = il._cost_derivatives(d, lambda dd, uu: cost(dd, uu), u)   # plain callable: finite differences
        an = cost.derivatives(d, u)
        np.testing.assert_allclose(an[0], fd[0], atol=1e-6)          # lx
        np.testing.assert_allclose(an[1], fd[1], atol=1e-6)          # lu
        np.testing.assert_allclose(an[3], fd[3], atol=1e-4)          # luu
        if lin is None:                                               # on the reference: exact Hessian
            np.testing.assert_allclose(an[2], fd[2], atol=2e-3)
            assert np.abs(an[2]).max() > 1e-2                        # a Hessian that could be wrong
        else:
            assert np.abs(an[0]).max() > 1e-2                        # a gradient that could be wrong
    with pytest.raises(ValueError, match="body 99"):
        BodyPointCost(m, 99, np.zeros(3))


@pytest.mark.parametrize("task_name", ["cheetah-vspeed", "walker-height", "jaco-palm-pose"])
def test_task_cost_gauss_newton_derivatives_match_finite_differences(task_name):
    """A task's iLQG cost (``BodyStateCost``): its value is minus the reward, its gradient equals
    the generic finite-difference one, and where the reward is quadratic in velocities (the
    cheetah's squared vertical speed) the velocity block of its Gauss-Newton Hessian is exact."""
    task = get_task(task_name)
    s = sim.make(task.system if task.system != "swimmer" else "swimmer6")
    m = s.model
    d, rng = _random_state(m, 5, 0.2)
    from gnwarp.control.tasks import sample_targets
    tg = sample_targets(task, s, 1, seed=0)
    cost = task_cost(m, task, None if tg is None else tg[0].numpy())
    u = 0.3 * rng.standard_normal(m.nu)
    il = ILQG(m, lambda dd, uu: 0.0, settings=ILQGSettings(horizon=2, nthread=1))
    fd = il._cost_derivatives(d, lambda dd, uu: cost(dd, uu), u)
    an = cost.derivatives(d, u)
    scale = max(1.0, np.abs(fd[0]).max())
    np.testing.assert_allclose(an[0], fd[0], atol=2e-4 * scale)            # lx
    np.testing.assert_allclose(an[1], fd[1], atol=1e-6)                    # lu (no action terms)
    assert np.abs(an[0]).max() > 0
    nx = 2 * m.nv + m.na
    assert an[2].shape == (nx, nx) and np.allclose(an[2], an[2].T)
    if task_name == "cheetah-vspeed":
        nv = m.nv
        np.testing.assert_allclose(an[2][nv:, nv:], fd[2][nv:, nv:], atol=2e-3 * max(1.0, np.abs(fd[2]).max()))
        assert np.abs(an[2][nv:, nv:]).max() > 0
