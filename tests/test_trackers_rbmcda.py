"""RBMCDA: birth and death probabilities against their formulas, and tracking on Table 2."""

import numpy as np
import pytest
from scipy.stats import binomtest, gamma, multivariate_normal

from trackers import metrics, models, rbmcda, scenarios


def model_and_prior():
    cfg = scenarios.Table2Config()
    m0, P0 = cfg.prior()
    return cfg, cfg.filter_model(), m0, P0


def test_birth_probability_of_first_measurement():
    """With no target alive the first measurement is a birth with probability
    p_b L_b / (p_b L_b + (1 - p_b) pi_c / V), L_b the new-target predictive density."""
    cfg, model, m0, P0 = model_and_prior()
    y = np.array([0.3, -0.4])
    N, pb, cp, cd = 4000, 0.2, 0.05, 1 / 16
    out = rbmcda.run([y[None]], model, m0, P0, rng=np.random.default_rng(0), dt=cfg.dt,
                     n_particles=N, birth_prob=pb, clutter_prior=cp, clutter_density=cd)
    # prior is at time 0, the measurement at time dt: predict the new-target prior first
    mp, Pp = model.A @ m0, model.A @ P0 @ model.A.T + model.Q
    Lb = multivariate_normal(model.H @ mp, model.H @ Pp @ model.H.T + model.R).pdf(y)
    p_birth = pb * Lb / (pb * Lb + (1 - pb) * cp * cd)
    n_born = round(out.expected_n_targets[0] * N)  # equal weights: the fraction with a target
    assert binomtest(n_born, N, p_birth).pvalue > 1e-3


@pytest.mark.slow
def test_lifetime_follows_gamma_survival():
    """A target born at step 0 and never measured again survives to time t with probability
    S(t - t_0) of the Gamma lifetime, S its survival function."""
    cfg, model, m0, P0 = model_and_prior()
    N, K = 3000, 150
    scans = [np.zeros((1, 2))] + [np.zeros((0, 2))] * (K - 1)
    out = rbmcda.run(scans, model, m0, P0, rng=np.random.default_rng(3), dt=cfg.dt,
                     n_particles=N, birth_prob=1.0, lifetime_shape=2.0, lifetime_scale=0.5)
    assert out.expected_n_targets[0] == pytest.approx(1.0)
    life = gamma(2.0, scale=0.5)
    for k in (20, 60, 100, 149):
        alive = round(out.expected_n_targets[k] * N)
        assert binomtest(alive, N, life.sf(k * cfg.dt)).pvalue > 1e-3


@pytest.mark.slow
def test_table2_numbers_births_deaths_and_ospa():
    """One monitoring node of Table 2, two seeds.

    - after each change in the true number of targets 0.3 s are left to settle; on the
      settled steps the reported number equals the truth on >= 70% of the steps;
    - births: within 1 s of t = 1 the reported number reaches 4;
    - deaths: within 0.6 s of each death (t = 3, 3.5, 4) it drops to the new true number
      (deaths are only inferred from the Gamma lifetime since the last association, whose
      mean is 1 s, so some lag is the model's), and it is 1 on most of the last 0.7 s;
    - the OSPA (c = 1, p = 2, positions) is below 0.35 of that of reporting no targets.
    Over 70 runs (10 seeds x 7 nodes, measured when the test was written) they held in 96%
    (settled), 100% (births), 97% (deaths), 97% (last stretch) and 100% (OSPA) of the runs,
    so these two seeds are a check, not a coin toss.
    """
    cfg, model, m0, P0 = model_and_prior()
    steps = np.round(np.array([1.0, 3.0, 3.5, 4.0]) / cfg.dt).astype(int)
    for ss in np.random.SeedSequence(21).spawn(2):
        data_rng, filt_rng = (np.random.default_rng(s) for s in ss.spawn(2))
        data = scenarios.simulate_table2(cfg, data_rng)
        out = rbmcda.run(data.nodes[2].scans, model, m0, P0, rng=filt_rng, dt=cfg.dt)
        est, true = out.n_targets, data.n_alive
        events = np.r_[0, np.flatnonzero(np.diff(true)) + 1]
        np.testing.assert_array_equal(events[1:], steps)
        settled = np.ones(len(true), bool)
        for e in events:
            settled[e:e + 30] = False
        assert np.mean(est[settled] == true[settled]) >= 0.7

        assert est[steps[0]:steps[0] + 100].max() >= 4  # the three births
        for e in steps[1:]:  # the three deaths
            assert np.any(est[e:e + 60] <= true[e]), e
        assert np.bincount(est[-70:]).argmax() == 1

        ospa, ospa_empty = [], []
        for k in range(len(true)):
            X = np.array([tr.mean[:2] for tr in out[k]]).reshape(-1, 2)
            Y = data.states_at(k)[:, :2]
            ospa.append(metrics.ospa(X, Y, 1.0, 2))
            ospa_empty.append(metrics.ospa(np.zeros((0, 2)), Y, 1.0, 2))
        assert np.mean(ospa) < 0.35 * np.mean(ospa_empty)


def test_tracks_structure():
    cfg, model, m0, P0 = model_and_prior()
    cfg = scenarios.Table2Config(n_steps=150)
    data = scenarios.simulate_table2(cfg, np.random.default_rng(4))
    out = rbmcda.run(data.nodes[4].scans, model, m0, P0, rng=np.random.default_rng(5),
                     dt=cfg.dt)
    assert len(out) == 150 and out.ess.shape == (150,)
    for step in out:
        ids = [tr.target_id for tr in step]
        assert len(set(ids)) == len(ids)
        for target_id, mean, cov in step:
            assert isinstance(target_id, int) and mean.shape == (4,) and cov.shape == (4, 4)
            assert np.all(np.linalg.eigvalsh(cov) > 0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"dt": 0.0}, "dt must be a finite positive"),
        ({"birth_prob": -0.1}, "birth_prob must be a probability"),
        ({"lifetime_shape": 0.0}, "lifetime_shape must be a finite positive"),
        ({"lifetime_scale": np.nan}, "lifetime_scale must be a finite positive"),
        ({"n_particles": 0}, "n_particles must be an integer >= 1"),
        ({"clutter_prior": 2.0}, "clutter_prior must be a probability"),
    ],
)
def test_rbmcda_rejects_bad_input(kwargs, match):
    _, model, m0, P0 = model_and_prior()
    args = {"rng": np.random.default_rng(0), "dt": 0.01} | kwargs
    with pytest.raises(ValueError, match=match):
        rbmcda.run([np.zeros((1, 2))], model, m0, P0, **args)


def test_rbmcda_unexplainable_measurement_raises():
    _, model, m0, P0 = model_and_prior()
    with pytest.raises(ValueError, match="birth_prob and clutter_prior must not both be 0"):
        rbmcda.run([np.zeros((1, 2))], model, m0, P0, rng=np.random.default_rng(0), dt=0.01,
                   birth_prob=0.0, clutter_prior=0.0)


def test_position_constant():
    assert models.POSITION == (0, 1)
