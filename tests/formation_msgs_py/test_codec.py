"""formation_msgs_py.codec without ROS: stamps, the stamped codecs and the ground-truth PoseArray.

Exact comparisons: encoding and decoding copy float64s into and out of bytes (struct), which no CPU,
SIMD path or libm can change; the quaternion <-> matrix conversions are compared with a tolerance
stated where they are.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from formation_msgs_py import codec


@pytest.mark.parametrize("rate", [1.0, 100.0, 1000.0, 3000.0, 7000.0, 10_000.0])
def test_step_stamps_are_whole_nanoseconds_within_half_a_nanosecond_of_k_over_rate(rate: float) -> None:
    """step_stamp_ns never drifts from k/rate by more than half a nanosecond (also where the period is not
    a whole number of nanoseconds), is strictly increasing, and control_time reads it back as ns/1e9."""
    ks = np.arange(0, 50_001)
    stamps = [codec.step_stamp_ns(int(k), rate) for k in ks]
    assert all(isinstance(s, int) for s in stamps[:10])
    exact = [int(k) * codec.NS_PER_S / rate for k in ks]  # k·1e9/rate, the correctly rounded float
    assert max(abs(s - e) for s, e in zip(stamps, exact)) <= 0.5
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert codec.control_time(stamps[3]) == stamps[3] / 1e9


def test_stamped_codecs_round_trip_any_stamp_and_value() -> None:
    """Twist, wrench and relative-pose codecs give back the stamp and the doubles they were given, bit for
    bit, whatever the frame name's length (the CDR padding depends on it)."""
    rng = np.random.default_rng(7)
    for agent in ("1", "22", "agent_with_a_long_name_3"):
        for make, n in ((codec.twist_codec, 6), (codec.wrench_codec, 6), (codec.relative_pose_codec, 7)):
            c = make(agent)
            for ns in (0, 1, 999_999_999, 1_000_000_000, 12_345_678_901_234):
                values = tuple(rng.normal(size=n).tolist())
                data = c.encode(ns, values)
                assert c.decode(data) == (ns, values)
                assert codec.stamp_of(data) == ns


def test_clock_bytes_carry_the_time() -> None:
    assert codec.stamp_of(codec.clock_bytes(5_000_000_123)) == 5_000_000_123
    assert len(codec.clock_bytes(0)) == 12  # encapsulation header, sec, nanosec


def test_ground_truth_round_trip() -> None:
    """Positions come back bit for bit; rotations through their quaternion within 1e-14: matrix -> quaternion
    -> matrix is about ten roundings (2.2e-16 each) of unit-size values, and a quaternion error enters each
    entry at most four times over (its quadratic forms): about 1e-14 at worst, on any libm."""
    rng = np.random.default_rng(3)
    p = rng.normal(size=(5, 3)).tolist()
    R = Rotation.random(5, random_state=4).as_matrix().tolist()
    ns, p_back, R_back = codec.ground_truth_from_bytes(codec.ground_truth_bytes(42, p, R))
    assert ns == 42
    assert p_back == p
    np.testing.assert_allclose(np.array(R_back), np.array(R), rtol=0, atol=1e-14)


def test_relative_pose_values_round_trip() -> None:
    """A relative pose's 7 doubles: the position as given, R back within the bound of the test above."""
    R = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix().tolist()
    values = codec.relative_pose_values([1.0, -2.0, 0.5], R)
    assert len(values) == 7 and values[:3] == (1.0, -2.0, 0.5)
    p_back, R_back = codec.relative_pose_from_values(values)
    assert p_back == [1.0, -2.0, 0.5]
    np.testing.assert_allclose(np.array(R_back), np.array(R), rtol=0, atol=1e-14)
