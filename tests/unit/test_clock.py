"""Virtual and manual clocks."""

import pytest

from autopower.runtime.clock import ManualClock, VirtualClock, WallClock


def test_virtual_clock_runs_speed_times_faster():
    wall = [1000.0]
    clock = VirtualClock(epoch_unix=1000.0, speed=20.0, wall_fn=lambda: wall[0])
    assert clock.now() == 0.0
    wall[0] = 1000.5
    assert clock.now() == pytest.approx(10.0)
    assert clock.wall_at(10.0) == pytest.approx(1000.5)
    assert clock.wall_at(clock.now()) == pytest.approx(wall[0])


def test_virtual_clock_before_epoch_is_negative():
    clock = VirtualClock(epoch_unix=1000.0, speed=2.0, wall_fn=lambda: 999.0)
    assert clock.now() == pytest.approx(-2.0)


@pytest.mark.parametrize("speed", [0, -1.0])
def test_speed_must_be_positive(speed):
    with pytest.raises(ValueError):
        VirtualClock(epoch_unix=0.0, speed=speed)


def test_wall_clock_is_speed_one():
    clock = WallClock(epoch_unix=0.0)
    assert clock.speed == 1.0
    assert clock.now() == pytest.approx(clock.wall(), abs=1.0)


def test_manual_clock():
    clock = ManualClock(speed=4.0, epoch_unix=100.0)
    assert clock.advance(2.0) == 2.0
    assert clock.wall() == pytest.approx(100.5)
    assert clock.wall_at(4.0) == pytest.approx(101.0)
    clock.set(3.0)
    with pytest.raises(ValueError):
        clock.advance(-1.0)
    with pytest.raises(ValueError):
        clock.set(1.0)
