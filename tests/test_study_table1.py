"""Table 1 fuses with the compiled backend and checks it against the conic reference on a
sample of steps of every run."""

import numpy as np

from studies import config as configs
from studies import table1


def _config(steps=4, n_steps=60):
    config = configs.load("table1")
    config["scenario"]["n_steps"] = n_steps
    config["check"]["steps"] = steps
    return config


def test_default_backend_is_newton_checked_against_clarabel():
    config = configs.load("table1")
    assert config["backend"] == "newton" and config["check"]["backend"] == "clarabel"


def test_a_run_reports_its_disagreement_with_the_reference():
    result, _ = table1.run_one(_config(), 1, np.random.SeedSequence(7))
    check = result[table1.CHECK]
    assert set(check) == set(table1.CHECKED)
    for row in table1.CHECKED:
        # Clarabel's unpolished objective is within its tolerance of the optimum, and the
        # certified optimum is never worse than it beyond rounding
        assert check[row]["abs"] < 1e-6 and check[row]["max"] <= 1e-13
        assert check[row]["abs"] >= abs(check[row]["max"])


def test_no_sampled_step_means_no_check():
    result, _ = table1.run_one(_config(steps=0), 1, np.random.SeedSequence(7))
    assert all(v == {"abs": 0.0, "max": 0.0} for v in result[table1.CHECK].values())
