"""Estimates: what it holds, that it is validated on construction by field (with the node,
time and track id of the culprit), and m = 0."""

import re

import numpy as np
import pytest

import fusion_opt as fo

M = np.array([[0.0, 1.0], [2.0, 3.0]])
C = np.array([np.eye(2), [[2.0, 0.5], [0.5, 1.0]]])


def test_holds_read_only_copies_with_default_ids():
    means = M.copy()
    e = fo.Estimates(means, C, time=2, node="radar")
    means[0, 0] = 99.0
    assert e.means[0, 0] == 0.0 and not e.means.flags.writeable
    assert e.ids.tolist() == [0, 1] and e.ids.dtype == np.int64
    assert (len(e), e.n, e.time, e.node) == (2, 2, 2.0, "radar")
    assert e.take([1]).ids.tolist() == [1] and e.take([1]).node == "radar"
    ids = np.array([7, 3], dtype=np.int64)  # ids already int64 are copied too, as a Group's
    e, g = fo.Estimates(M, C, ids), fo.Group(("a", "b"), ids, M, C)
    ids[0] = 5
    assert e.ids.tolist() == g.ids.tolist() == [7, 3] and ids.flags.writeable
    # fuzz T2: a long long (int64's twin on Linux) is stored as int64, not as itself
    e = fo.Estimates(M, C, np.array([7, 3], dtype=np.longlong))
    assert e.ids.dtype == np.int64 and isinstance(e.ids[0], np.int64)
    # ... and masked ids are refused, as masked means are: their hidden values were read
    for mask in ([True, False], [True, True]):
        masked = np.ma.MaskedArray(np.array([5, 6]), mask=mask)
        with pytest.raises(fo.FusionInputError, match="ids is a masked array"):
            fo.Estimates(M, C, masked)
        with pytest.raises(fo.FusionInputError, match="ids is a masked array"):
            fo.Group(("a", "b"), masked, M, C)


def test_covariances_are_symmetrised_within_the_tolerance():
    P = np.array([[1.0, 0.5], [0.5 + 1e-12, 1.0]])
    e = fo.Estimates(M[:1], P[None])
    np.testing.assert_array_equal(e.covs[0], e.covs[0].T)


def test_empty_and_its_hint():
    e = fo.Estimates.empty(4, time=1.0, node="a")
    assert (len(e), e.n, e.means.shape, e.covs.shape) == (0, 4, (0, 4), (0, 4, 4))
    with pytest.raises(fo.FusionInputError, match=r"Estimates.empty\(n\)"):
        fo.Estimates([], [], [])


@pytest.mark.parametrize("kwargs, match", [
    (dict(covs=C[:1]), r"covs must have shape \(2, 2, 2\)"),
    (dict(covs=C * [[[1.0]], [[-1.0]]]), r"covs of estimate 1 \(id 1\) is not positive"),
    (dict(means=M + [[0.0, np.inf], [0.0, 0.0]]), r"means has a non-finite value inf"),
    (dict(means=M.astype(complex)), "means must be an array of real numbers, got complex"),
    (dict(ids=[3, 3]), r"ids must be unique within one Estimates, got \[3, 3\]"),
    (dict(ids=["a", "b"]), "ids must be integers .*got strings"),
    (dict(ids=[[1, 2], [3]]), "ids must be integers .*array of real numbers"),
    (dict(ids=[1.5, 2.0]), "ids must be integers"),
    (dict(ids=[1]), r"ids must have shape \(2,\)"),
    (dict(time=float("nan")), "time must be a finite real number"),
    (dict(node=["unhashable"]), "node must be hashable"),
    (dict(node=np.timedelta64(5)), "node must be hashable"),  # hash() raised ValueError
])
def test_a_bad_field_is_refused_by_name(kwargs, match):
    args = dict(means=M, covs=C, ids=None, time=None, node=None) | kwargs
    with pytest.raises(fo.FusionInputError, match=match):
        fo.Estimates(**args)


class _Echo:
    """A tracker whose step returns its scan."""

    def step(self, scan):
        return scan


def test_a_timedelta64_time_is_shown_as_itself_where_it_is_refused():
    """fuzz5 1: the item of a unitless np.timedelta64(5) is the int 5, so Estimates, a
    processing node's and a network's step refused it with "time must be a finite real
    number or None, got 5", naming a valid time."""
    one = fo.Estimates(M[:1], C[:1])
    def node():
        return fo.ProcessingNode(["a"], method="bci", threshold=1.0)

    calls = {"Estimates": lambda t: fo.Estimates(M, C, time=t),
             "ProcessingNode": lambda t: node().step({"a": one}, time=t),
             "Network": lambda t: fo.Network({"a": _Echo()}, {}).step({"a": one}, time=t)}
    for t, shown in ((np.timedelta64(5), r"np.timedelta64\(5\)"),
                     (np.datetime64(5, "s"), r"np.datetime64\('1970-01-01T00:00:05'\)")):
        for call in calls.values():
            with pytest.raises(fo.FusionInputError,
                               match=f"time must be a finite real number or None, got {shown}$"):
                call(t)


def test_errors_name_the_node_the_time_and_the_track_id():
    bad = C.copy()
    bad[1, 0, 1] = 3.0  # not symmetric
    with pytest.raises(fo.FusionInputError, match=r"^Estimates of node 'radar3' at time 1.5: "
                                                    r"covs of estimate 1 \(id 17\) is not sym"):
        fo.Estimates(M, bad, [7, 17], time=1.5, node="radar3")


def test_extreme_values_are_kept_exactly():
    """Regression: symmetrising 1e308 I as (P + P^T) / 2 overflowed to inf, and integer ids
    went through float64, where 2^53 + 1 became 2^53 (a clash)."""
    e = fo.Estimates(np.zeros((1, 2)), 1e308 * np.eye(2)[None])
    np.testing.assert_array_equal(e.covs[0], 1e308 * np.eye(2))
    tiny = np.array([[[5e-324, 0.0], [0.0, 5e-324]]])  # subnormal: halved first, it is 0
    np.testing.assert_array_equal(fo.Estimates(np.zeros((1, 2)), tiny).covs, tiny)
    ids = fo.Estimates(np.zeros((2, 2)), np.stack([np.eye(2)] * 2), [2**53, 2**53 + 1]).ids
    assert ids.tolist() == [2**53, 2**53 + 1]


@pytest.mark.parametrize("scale", [1e-318, 1e-300, 1.0, 1e300, 5e307])
def test_definiteness_is_decided_at_every_scale(scale):
    """c [[2, 1], [1, 2]] (eigenvalues 3c, c) is kept exactly and c [[1, 2], [2, 1]]
    (3c, -c) refused, naming the estimate, from subnormal c to entries near 1.8e308."""
    good, bad = scale * np.array([[2.0, 1.0], [1.0, 2.0]]), scale * np.array([[1.0, 2.0],
                                                                            [2.0, 1.0]])
    np.testing.assert_array_equal(fo.Estimates(M, np.stack([good, good])).covs[1], good)
    with pytest.raises(fo.FusionInputError, match=r"covs of estimate 1 \(id 1\) is not pos"):
        fo.Estimates(M, np.stack([good, bad]))


def test_take_positions_or_a_mask_and_refuses_the_rest():
    """Regression: take([5]) raised IndexError, take([0.5]) truncated to 0, and a boolean
    mask was read as positions 1 and 0."""
    e = fo.Estimates(np.arange(6.0).reshape(3, 2), np.stack([np.eye(2)] * 3), [7, 8, 9])
    assert e.take([True, False, True]).ids.tolist() == [7, 9]
    assert e.take([2, -3]).ids.tolist() == [9, 7] and len(e.take([])) == 0
    for bad in ([3], [0.5], "a", None, [True]):
        with pytest.raises(fo.FusionInputError, match=r"integer positions in \[-3, 3\)"):
            e.take(bad)


def test_a_node_name_must_work_as_a_key():
    """Regression: a tuple holding a list passed isinstance(node, Hashable)."""
    with pytest.raises(fo.FusionInputError, match="node must be hashable"):
        fo.Estimates(np.zeros((1, 2)), np.eye(2)[None], node=(1, [2]))


def test_a_group_made_by_hand_is_checked():
    """Regression: lists raised AttributeError (setflags) and nothing was checked."""
    g = fo.Group(("a", "b"), [1, 1], [[0.0, 0.0], [1.0, 1.0]], [np.eye(2)] * 2)
    assert g.pairs == (("a", 1), ("b", 1)) and not g.covs.flags.writeable
    for args, match in (((("a",), [1], [[0.0, 0.0]], [-np.eye(2)]), "not positive definite"),
                        ((("a", "a"), [1, 2], [[0, 0], [1, 1]], [np.eye(2)] * 2), "distinct"),
                        ((("a",), [1.5], [[0.0, 0.0]], [np.eye(2)]), "ids must be integers"),
                        ((("a", "b"), [1], [[0.0, 0.0]], [np.eye(2)]), "2 sources but 1")):
        with pytest.raises(fo.FusionInputError, match=match):
            fo.Group(*args)


def test_every_int64_id_is_kept_and_one_beyond_is_refused_with_its_value():
    """Fuzz G2: ids at or beyond 2^62 were refused as not fitting 64 bits (hash() of a
    track name lands there half the time)."""
    means, covs = np.zeros((3, 2)), np.tile(np.eye(2), (3, 1, 1))
    ids = [2**62, 2**63 - 1, -(2**63)]
    assert fo.Estimates(means, covs, ids).ids.tolist() == ids
    assert fo.Estimates(means, covs, [2.0**62, 3.0, -(2.0**63)]).ids.tolist() == [2**62, 3,
                                                                              -(2**63)]
    for bad, shown in [(np.array([1, 2, 2**63], dtype=np.uint64), "9223372036854775808"),
                       ([1.0, 2.0, 2.0**63], "9.223372036854776e+18"),
                       ([1, 2, 2**64], "18446744073709551616"),
                       ((1, 2, -(2**63) - 1), "-9223372036854775809")]:
        with pytest.raises(fo.FusionInputError, match=rf"ids must fit in a signed 64-bit "
                           rf"integer \(-2\^63 to 2\^63 - 1\), got {re.escape(shown)}$"):
            fo.Estimates(means, covs, bad)


def test_ids_above_2_53_from_any_container_are_kept_exactly():
    """Fuzz K1: ids in an object array (a table's column), a list mixing numpy integers with
    a uint64 or a float, or long doubles went through float64: 2^62 + 1 became 2^62, and
    two ids 1 apart were refused as equal numbers the caller never passed."""
    means, covs = np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1))
    big = 2**62 + 1
    for ids in (np.array([big, 5], dtype=object), [big, np.uint64(5)], [np.int64(big), 5.0],
                np.array([big, 5], dtype=np.longdouble), (big, np.int32(5))):
        assert fo.Estimates(means, covs, ids).ids.tolist() == [big, 5], ids
    assert fo.Estimates(means, covs, np.array([big, big - 1], dtype=object)).ids.tolist() \
        == [big, big - 1]
    for bad, said in (([np.float64(1.5), 2], "got 1.5 at index 0"),
                      (np.array([2, np.nan], dtype=object), "got nan at index 1"),
                      ([np.uint64(2**63), 1], r"64-bit integer .*got 9223372036854775808$")):
        with pytest.raises(fo.FusionInputError, match=said):
            fo.Estimates(means, covs, bad)


def test_decimal_ids_from_a_database_column_are_read_exactly():
    """Fuzz L leftover: Decimals (a NUMERIC column) were refused as "not numbers"; whole
    ones are ids, read exactly past 2^53 (in a list, a tuple or an object array), and the
    others are refused by value, as ints and floats are."""
    from decimal import Decimal

    means, covs = np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1))
    big = 2**62 + 1
    for ids in ([Decimal(big), Decimal("5.000")], (Decimal(big), Decimal(5)),
                np.array([Decimal(big), Decimal(5)], dtype=object)):
        assert fo.Estimates(means, covs, ids).ids.tolist() == [big, 5], ids
    for bad, said in (([Decimal("1.5"), Decimal(2)], r"got Decimal\('1.5'\) at index 0"),
                      ([Decimal(1), Decimal("NaN")], r"got Decimal\('NaN'\) at index 1"),
                      ([Decimal(2**63), Decimal(1)], r"64-bit integer .*got 9223372036854775808$"),
                      ([Decimal(1)], r"shape \(2,\)"),
                      ([Decimal(1), Decimal(1)], "unique"),
                      # fuzz O3, O4: refused by exponent (int() of 1E+1000000 took 75 s)
                      # and named without the repr of a 5,001-digit int (a ValueError)
                      ([Decimal("1E+1000000"), Decimal(1)], r"got Decimal\('1E\+1000000'\)$"),
                      ([10**5000, 1], "got an integer of about 5001 digits$")):
        with pytest.raises(fo.FusionInputError, match=said):
            fo.Estimates(means, covs, bad)


def test_an_integer_time_beyond_2_53_is_refused_everywhere_a_time_is_given():
    """Fuzz K6: nanoseconds since 1970 (1.7e18) became a float 128 ns off; two stamps 60 ns
    apart merged and a step back in time passed the forward check. Refused, with what to
    give instead; 2^53 itself and floats of any size are times as before."""
    from trackers import kalman, models

    t = 1_700_000_000_000_000_100
    one = (np.zeros((1, 2)), np.eye(2)[None], None)
    for stamp in (t, np.int64(t), -t, 2**53 + 1):
        with pytest.raises(fo.FusionInputError, match=r"is an integer beyond 2\^53.*seconds"):
            fo.Estimates(*one, stamp)
    assert fo.Estimates(*one, 2**53).time == 2.0**53
    assert fo.Estimates(*one, float(t)).time == float(t)
    node = fo.ProcessingNode(["a"], method="bci", threshold=1.0)
    with pytest.raises(fo.FusionInputError, match="integer beyond 2"):
        node.step({"a": fo.Estimates(*one)}, time=np.int64(t))
    kf = kalman.KalmanFilter(models.LinearGaussian(np.eye(2), np.eye(2), np.eye(2), np.eye(2)),
                             np.zeros(2), np.eye(2))
    with pytest.raises(fo.FusionInputError, match="integer beyond 2"):
        kf.step([], time=t)
    assert kf.steps == 0


def test_float16_ids_and_long_times_are_refused_or_kept_without_warnings():
    """Fuzz L2, L8: float16 ids warned (an overflow comparing them with 2^63), which
    -W error turned into a crash; a time of 1,000 digits was printed whole, twice."""
    import warnings

    one = (np.zeros((1, 2)), np.eye(2)[None])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fo.Estimates(*one, np.array([7.0], dtype=np.float16)).ids.tolist() == [7]
        with pytest.raises(fo.FusionInputError) as info:
            fo.Estimates(*one, None, -10**1000, "n")
    assert len(str(info.value)) < 300 and "(1002 digits)" in str(info.value)
    # a value that is not an int is shown whole, not cut and called digits (fuzz of
    # 2026-11-29: "datetime... (38 digits)")
    with pytest.raises(fo.FusionInputError) as info:
        fo.Estimates(*one, time=np.datetime64("2026-01-01T00:00:01"))
    assert "got np.datetime64('2026-01-01T00:00:01')" in str(info.value)  # as given (fuzz5 1)
    assert "digits" not in str(info.value)


def test_a_whole_time_beyond_2_53_of_another_type_that_float64_rounds_is_refused():
    """Fuzz L1: Fraction(2^53 + 1) and a long double 2^53 + 1 were rounded to 2^53 as
    silently as integers were (K6); a Fraction of 1/3, a float32 of 1e20 and a long double
    of 0.1 are times as before."""
    from fractions import Fraction

    one = (np.zeros((1, 1)), np.ones((1, 1, 1)), None)
    for t in (Fraction(2**53 + 1), np.longdouble(2**53) + np.longdouble(1)):
        with pytest.raises(fo.FusionInputError, match="is an integer beyond 2"):
            fo.Estimates(*one, t)
    assert fo.Estimates(*one, Fraction(1, 3)).time == 1 / 3
    assert fo.Estimates(*one, np.float32(1e20)).time == float(np.float32(1e20))
    assert fo.Estimates(*one, np.longdouble(0.1)).time == 0.1


def test_an_empty_object_array_of_ids_is_no_ids():
    """Fuzz L3: an empty object array (a table's empty column) was refused as "objects
    (ragged or not numbers)" where [] is accepted."""
    e = fo.Estimates(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.array([], dtype=object))
    assert len(e) == 0 and e.ids.dtype == np.int64
