"""Exact discretisation of the turn model against closed forms and numerical quadrature."""

import dataclasses
import warnings

import numpy as np
import pytest
from scipy.integrate import quad_vec
from scipy.linalg import expm

from fusion_opt import FusionInputError
from trackers import models


def cv_closed_form(q, dt):
    """Constant-velocity A and Q in closed form (Bar-Shalom, white-noise acceleration)."""
    I2 = np.eye(2)
    A = np.block([[I2, dt * I2], [0 * I2, I2]])
    Q = q * np.block([[dt**3 / 3 * I2, dt**2 / 2 * I2], [dt**2 / 2 * I2, dt * I2]])
    return A, Q


@pytest.mark.parametrize("dt", [0.01, 0.025, 1.0])
def test_discretize_a0_equals_constant_velocity(dt):
    A, Q = models.discretize(models.turn_F(0.0), models.turn_L(), 0.1 * np.eye(2), dt)
    A_ref, Q_ref = cv_closed_form(0.1, dt)
    np.testing.assert_allclose(A, A_ref, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(Q, Q_ref, rtol=1e-10, atol=1e-15)


@pytest.mark.parametrize(("a", "dt"), [(np.pi / 4.2, 0.025), (-1.0, 0.5), (3.08, 0.3)])
def test_discretize_turning_matches_quadrature(a, dt):
    F, L, Qc = models.turn_F(a), models.turn_L(), np.diag([0.1, 0.3])
    A, Q = models.discretize(F, L, Qc, dt)

    def integrand(s):
        E = expm(F * s)
        return E @ L @ Qc @ L.T @ E.T

    Q_ref, _ = quad_vec(integrand, 0.0, dt, epsabs=1e-14, epsrel=1e-12)
    np.testing.assert_allclose(Q, Q_ref, rtol=1e-9, atol=1e-14)
    # velocity block of A is the rotation by a dt (closed form of expm for the turn model)
    c, s = np.cos(a * dt), np.sin(a * dt)
    np.testing.assert_allclose(A[2:, 2:], [[c, s], [-s, c]], atol=1e-12)
    np.testing.assert_allclose(A[:2, 2:], [[s / a, (1 - c) / a], [-(1 - c) / a, s / a]],
                               atol=1e-12)
    np.testing.assert_allclose(Q, Q.T, atol=0)
    assert np.all(np.linalg.eigvalsh(Q) > 0)


def test_linear_gaussian_is_frozen_and_read_only():
    model = models.turn_model(0.0, 0.1, 0.05, 0.025)
    assert (model.n, model.d) == (4, 2)
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.A = np.eye(4)
    with pytest.raises(ValueError):
        model.A[0, 0] = 2.0
    # fuzz6 1: a pickled or copied model's arrays came back writeable (a deep-copied
    # filter's model.R could then be set negative in place)
    import copy
    import pickle

    for made in (pickle.loads(pickle.dumps(model)), copy.copy(model), copy.deepcopy(model)):
        for name in "AQHR":
            got = getattr(made, name)
            assert not got.flags.writeable, name
            np.testing.assert_array_equal(got, getattr(model, name))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"A": np.eye(3)}, "Q must have shape"),
        ({"A": np.full((4, 4), np.nan)}, "A contains non-finite"),
        ({"H": np.eye(2, 3)}, r"H must be \(d, 4\) with d >= 1"),
        ({"R": -np.eye(2)}, "R must be positive definite"),
        ({"Q": np.diag([1.0, 1.0, 1.0, -1.0])}, "Q must be positive semidefinite"),
        ({"R": np.array([[1.0, 0.5], [0.0, 1.0]])}, "R must be symmetric"),
        # regression: a complex A was truncated to its real part with a ComplexWarning
        ({"A": np.eye(4) + 0.1j * np.eye(4)}, "A must be an array of real numbers, got complex"),
        ({"H": [[True, False, False, False], [False, True, False, False]]}, "H must be"),
        ({"Q": "eye"}, "Q must be an array of real numbers"),
        ({"R": None}, "R must be an array of real numbers"),
        # fuzz E5: below scale 1 the tolerances were absolute (1e-12, 1e-10) and let these
        # pass: an R whose symmetric part is indefinite, a negative definite Q
        ({"R": np.array([[1e-20, 1e-14], [0.0, 1e-20]])}, "R must be symmetric"),
        ({"Q": -5e-11 * np.eye(4)}, "Q must be positive semidefinite"),
    ],
)
def test_linear_gaussian_rejects_bad_input(kwargs, match):
    args = {"A": np.eye(4), "Q": np.eye(4), "H": np.eye(2, 4), "R": np.eye(2)} | kwargs
    with pytest.raises(ValueError, match=match):
        models.LinearGaussian(**args)


@pytest.mark.parametrize("scale", [1e-300, 1e-20, 1.0, 1e20, 1e300])
def test_a_valid_model_at_any_scale_is_accepted(scale):
    """The checks are relative to each matrix's own scale: a model scaled as a whole is as
    valid at 1e-300 as at 1 (a singular PSD Q included)."""
    Q = scale * np.diag([1.0, 1.0, 0.0, 0.0])
    R = scale * np.array([[2.0, 0.5], [0.5, 1.0]])
    model = models.LinearGaussian(np.eye(4), Q, np.eye(2, 4), R)
    np.testing.assert_array_equal(model.R, R)


def test_discretize_rejects_bad_input():
    F, L = models.turn_F(0.0), models.turn_L()
    with pytest.raises(ValueError, match="dt must be a finite positive"):
        models.discretize(F, L, np.eye(2), 0.0)
    with pytest.raises(ValueError, match=r"L must be \(4, s\) with s >= 1"):
        models.discretize(F, L.T, np.eye(2), 0.1)
    with pytest.raises(ValueError, match="F must be square"):
        models.discretize(F[:3], L, np.eye(2), 0.1)
    with pytest.raises(ValueError, match="turn rate"):
        models.turn_F(np.inf)
    for bad in ("0.1", 1j, None, True):  # regression: float("0.1") and float(True) passed
        with pytest.raises(FusionInputError, match="turn rate"):
            models.turn_F(bad)
        with pytest.raises(FusionInputError, match="dt must be a real number"):
            models.turn_model(0.0, 0.1, 0.05, bad)


def test_a_step_whose_model_overflows_names_dt():
    """Regression: dt = 1e300 was refused as "A contains non-finite values", an argument
    the caller never gave."""
    with pytest.raises(FusionInputError, match="dt = 1e[+]300 is too long a step"):
        models.turn_model(0.0, 1.0, 1.0, 1e300)
    # fuzz N6: |F|_1 dt overflowed at 1e308 and int(inf) raised OverflowError
    for dt in (1e308, np.finfo(float).max):
        with pytest.raises(FusionInputError, match="is too long a step"):
            models.turn_model(0.0, 1.0, 1.0, dt)
        with pytest.raises(FusionInputError, match="is too long a step"):
            models.discretize(models.turn_F(0.5), models.turn_L(), np.eye(2), dt)
    with warnings.catch_warnings():  # fuzz N12: q = 1e308 warned of an overflow
        warnings.simplefilter("error")
        assert np.isfinite(models.turn_model(0.0, 1e308, 0.05, 0.025).Q).all()
    with pytest.raises(FusionInputError, match="A must be square with n >= 1"):
        models.LinearGaussian(*(np.zeros((0, 0)),) * 4)


@pytest.mark.parametrize("F, L, dt", [
    ([[0.0, 1.0], [0.0, -50.0]], [[0.0], [1.0]], 1.0),   # Q was not even PSD
    ([[-20.0, 100.0], [0.0, -20.0]], np.eye(2), 1.0),    # Q[0, 0] 121.6 for 0.3375
    ([[0.0, 1.0], [0.0, -20.0]], [[0.0], [1.0]], 5.0)])  # relative error 4e25
def test_discretize_of_a_stiff_model_against_quadrature(F, L, dt):
    """Regression: Van Loan's exponential holds expm(-F dt), huge for a stable F over a
    long step, which cancelled in Q; now over dt / 2^s, doubled s times. Reference: the
    integral of expm(F t) L Qc L^T expm(F t)^T over [0, dt] by scipy's quad_vec."""
    F, L = np.array(F), np.array(L, dtype=float)
    Qc = np.eye(L.shape[1])
    A, Q = models.discretize(F, L, Qc, dt)
    ref = quad_vec(lambda t: expm(F * t) @ L @ Qc @ L.T @ expm(F * t).T, 0.0, dt,
                   epsabs=1e-14, epsrel=1e-12)[0]
    np.testing.assert_allclose(Q, ref, rtol=1e-10, atol=1e-13 * np.abs(ref).max())
    np.testing.assert_allclose(A, expm(F * dt), rtol=1e-12, atol=1e-15)
    # a very stable mode is no longer refused as overflowing: A = 0, Q = Qc / (2 lambda)
    A, Q = models.discretize(np.diag([-800.0, -1.0]), np.eye(2), np.eye(2), 1.0)
    np.testing.assert_allclose(Q[0, 0], 1 / 1600, rtol=1e-12)
    with pytest.raises(FusionInputError, match="too long a step for this F"):
        models.turn_model(1e300, 0.1, 0.1, 0.05)


@pytest.mark.parametrize("dt", [0.5, 1e6, 5.6e17, 1e24, 1e300])
def test_a_long_step_without_dynamics_gives_the_closed_form_noise(dt):
    """Fuzz O8: with F = 0, Q = L Qc L^T dt and A = I exactly; at dt = 1e24 scipy's expm
    of Van Loan's nilpotent block matrix gave a Q off by 100% and indefinite. Against the
    closed form, and for a small F (|F| dt = 1e-8) against its first-order expansion."""
    L, Qc = np.array([[1.0], [2.0]]), np.array([[3.0]])
    A, Q = models.discretize(np.zeros((2, 2)), L, Qc, dt)
    np.testing.assert_array_equal(A, np.eye(2))
    np.testing.assert_allclose(Q, L @ Qc @ L.T * dt, rtol=1e-14)
    F = np.array([[0.0, 1.0], [0.0, 0.0]]) * (1e-8 / dt)
    A, Q = models.discretize(F, L, Qc, dt)
    np.testing.assert_allclose(Q, L @ Qc @ L.T * dt, rtol=1e-7)
    assert np.linalg.eigvalsh(Q).min() >= -1e-12 * np.abs(Q).max()


def test_a_process_noise_near_the_float64_limit_stays_finite():
    """Fuzz3 F1: Q = Qc dt = 1e308 is representable, but the final symmetrisation
    0.5 * (Q + Q.T) overflowed to inf after the finiteness check (a RuntimeWarning only),
    and turn_model then refused its own Q. Against the closed form Q = L Qc L^T dt."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for Qc, dt in ((1e308, 1.0), (1.0, 1e308), (1.7e308, 1.0)):
            A, Q = models.discretize([[0.0]], [[1.0]], [[Qc]], dt)
            np.testing.assert_array_equal(Q, [[Qc * dt]])
        Q = models.turn_model(0.0, 1e308, 1.0, 1.0).Q
    np.testing.assert_allclose(Q[[0, 0, 2], [0, 2, 2]], [1e308 / 3, 1e308 / 2, 1e308],
                               rtol=1e-15)


@pytest.mark.parametrize("a", [1e12, 1e15, 1e17, 1.8e18])
def test_a_turn_whose_doublings_lose_the_rotation_is_refused(a):
    """Fuzz U8: over dt = 0.1 these turn rates need 38 to 62 doublings, each doubling the
    rounding of the rotation: its singular values were 1.0000129 (1e12), 1.54 (1e17) and
    1.8e-5 (1.8e18) where a rotation's are 1. Refused now: log det A drifts from
    tr(F) dt = 0, which it equals exactly."""
    with pytest.raises(FusionInputError, match=r"dt = 0.1 is too long a step for this F: .* "
                                               r"has log det .* where tr\(F\) dt = 0 "):
        models.turn_model(a, 0.05, 0.01, 0.1)


@pytest.mark.parametrize("a, dt", [(1e5, 0.1), (1e8, 0.1), (0.0, 1e9), (0.75, 1e6)])
def test_long_turns_that_keep_their_rotation_are_accepted(a, dt):
    """The check of U8 refuses no model whose doublings keep it: the velocity block is a
    rotation to 1e-8 (against cos and sin of a dt) and the constant-velocity model over 1e9 s
    is exact, as its doublings are."""
    A = models.turn_model(a, 0.05, 0.01, dt).A
    c, s = np.cos(a * dt), np.sin(a * dt)
    np.testing.assert_allclose(A[2:, 2:], [[c, s], [-s, c]], atol=1e-8)  # vx' = a vy
    np.testing.assert_allclose(np.linalg.svd(A[2:, 2:], compute_uv=False), 1.0, atol=1e-8)
    if a == 0.0:
        np.testing.assert_array_equal(A, [[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]])


def test_the_doubling_check_passes_models_whose_determinant_it_cannot_resolve():
    """U8's check compares log det A with tr(F) dt only where the LU resolves it: not for a
    stiff model whose A underflows, nor a hyperbolic one of condition 1e26 (against cosh and
    sinh)."""
    A = models.discretize(np.diag([-800.0, 200.0]), np.eye(2), np.eye(2), 1.0)[0]
    assert A[0, 0] == 0.0 and A[1, 1] == pytest.approx(np.exp(200.0), rel=1e-12)
    A = models.discretize(np.array([[0.0, 1.0], [1.0, 0.0]]), np.eye(2), np.eye(2), 30.0)[0]
    np.testing.assert_allclose(A, [[np.cosh(30), np.sinh(30)], [np.sinh(30), np.cosh(30)]],
                               rtol=1e-12)
