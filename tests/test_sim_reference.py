"""The physical limit of the simulator's tracks (tmrl.sim.reference): the planned lap respects the
car's limits, the driver completes it in the simulator close to the plan, and both beat the
centre-line driver."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from tmrl.sim import reference
from tmrl.sim.car import CarParams
from tmrl.sim.reference import (
    PlanDriver,
    drive_lap,
    plan_lap,
    reference_lap,
    reference_lap_time,
    speed_limits,
    speed_profile,
)
from tmrl.sim.track import TRACK_NAMES, named_track

DOCS = Path(__file__).resolve().parents[1] / "docs" / "simulator.md"

#: Driven laps may beat the plan by this share (the physics steps 12.5 ms, the plan 0.25 m).
DISCRETISATION = 0.005
#: The driven reference lap is within this share of the planned bound.
CLOSE = 0.02


@pytest.mark.parametrize("name", TRACK_NAMES)
def test_reference_lap_is_driven_close_to_the_plan_and_beats_the_centre_line(name):
    ref = reference_lap(name, centre_line=True)
    assert ref.track == name
    assert ref.wall_hits == 0
    assert ref.planned * (1 - DISCRETISATION) <= ref.driven <= ref.planned * (1 + CLOSE)
    assert ref.driven < 0.8 * ref.centre_line  # the centre-line driver is far from the limit
    assert reference_lap_time(name) == ref.driven


@pytest.mark.parametrize("name", TRACK_NAMES)
def test_planned_speeds_stay_within_the_cars_limits(name):
    plan = plan_lap(name)
    p, ds, v, k = plan.params, plan.spacing, plan.speed, plan.curvature
    assert v[0] == 0.0 and len(v) == len(plan.points) + 1  # from a standstill, round to the finish
    assert np.all(v[:-1] <= plan.limit + 1e-9) and np.all(v <= p.top_speed)
    # grip: lateral acceleration v^2 |k| at most `grip`; steering: |k| within the lock at speed v
    assert np.all(v[:-1] ** 2 * np.abs(k) <= p.grip * (1 + 1e-9))
    assert np.all(np.abs(k) <= np.tan(p.max_steer / (1 + v[:-1] / p.steer_speed)) / p.wheelbase + 1e-12)
    # engine and brakes between consecutive points (the acceleration at the lower speed is the
    # engine's best, the deceleration at the higher speed the brakes' best)
    gain = v[1:] ** 2 - v[:-1] ** 2
    engine = p.engine * (1 - v[:-1] / p.top_speed) - p.drag * v[:-1] ** 2 - p.rolling
    brakes = p.brake + p.drag * v[:-1] ** 2 + p.rolling
    assert np.all(gain <= 2 * engine * ds + 1e-9)
    assert np.all(-gain <= 2 * brakes * ds + 1e-9)
    # the plan is at the limits, not merely within them: full gas, full brakes (the oval's bends
    # tighten slowly enough to need none), at the grip's limit in the bends
    assert np.any(gain > 1.99 * engine * ds)
    assert np.any(-gain > 1.99 * brakes * ds) or name == "oval"
    assert np.mean(np.abs(v[:-1] - plan.limit) < 1e-6) > 0.05
    assert plan.lap_time == pytest.approx(np.sum(2 * ds / (v[1:] + v[:-1])))


@pytest.mark.parametrize("name", TRACK_NAMES)
def test_racing_line_stays_on_the_road_and_is_straighter_than_the_centre_line(name):
    track = named_track(name)
    plan = plan_lap(track)
    room = track.half_width - plan.params.radius - reference.MARGIN
    _, lateral = reference._lateral(track, plan.points)
    # within 2 cm (the smooth line between control points 1 m apart cuts a bend's chord a little)
    assert np.max(np.abs(lateral)) <= room + 0.02
    assert np.max(np.abs(lateral)) > room - 0.01  # it uses the road's width
    assert np.linalg.norm(plan.points[0] - track.centre[0]) < 0.01  # from where the car starts
    assert np.max(np.abs(plan.curvature)) < 0.8 * np.max(np.abs(track.curvature))
    assert plan.length == pytest.approx(track.length, rel=0.1)


def test_speed_profile_known_answers():
    # no drag, no rolling, an engine that never fades: v^2 = 2 a s out of the start, v^2 = vc^2 +
    # 2 b (sc - s) braking into a slow section
    p = CarParams(engine=5.0, top_speed=1e12, brake=10.0, drag=0.0, rolling=0.0)
    ds, n = 0.5, 401  # 200 m
    s = ds * np.arange(n)
    limit = np.full(n, 1e6)
    slow = (s >= 150.0) & (s <= 160.0)
    limit[slow] = 8.0
    v = speed_profile(limit, ds, p)
    free = s <= 60.0
    assert v[free] == pytest.approx(np.sqrt(2 * 5.0 * s[free]), rel=1e-9)
    braking = (s >= 130.0) & (s < 150.0)
    assert v[braking] == pytest.approx(np.sqrt(64.0 + 2 * 10.0 * (150.0 - s[braking])), rel=1e-9)
    assert np.all(v[slow] == 8.0)
    after = s > 160.0
    assert v[after] == pytest.approx(np.sqrt(64.0 + 2 * 5.0 * (s[after] - 160.0)), rel=1e-9)
    # the lap ends anywhere: nothing brakes for the finish line
    assert v[-1] == pytest.approx(math.sqrt(64.0 + 2 * 5.0 * 40.0))


def test_speed_profile_reaches_the_cars_terminal_speed_on_a_long_straight():
    p = CarParams()
    v = speed_profile(np.full(20001, 1e6), 0.5, p)  # 10 km
    terminal = v[-1]
    # the engine's push equals drag and rolling resistance there
    assert p.engine * (1 - terminal / p.top_speed) == pytest.approx(p.drag * terminal ** 2 + p.rolling, abs=1e-3)


def test_speed_limits_from_grip_and_steering():
    p = CarParams()
    assert speed_limits(np.array([0.0]), p)[0] == p.top_speed
    k = np.array([1 / 50.0, -1 / 20.0])
    assert speed_limits(k, p) == pytest.approx(np.sqrt(p.grip / np.abs(k)))  # grip binds
    # little grip left aside, the steering lock binds: tan(lock at v) / wheelbase is exactly the curvature
    slippery = CarParams(grip=1e6)
    v = speed_limits(np.array([1 / 10.0]), slippery)[0]
    assert math.tan(slippery.max_steer / (1 + v / slippery.steer_speed)) / slippery.wheelbase == pytest.approx(1 / 10.0)
    # a bend tighter than the lock at a standstill cannot be driven at all
    assert speed_limits(np.array([1.0]), p)[0] == 0.0


@pytest.mark.parametrize("name", TRACK_NAMES)
def test_the_plan_can_be_driven_at_the_environments_pace(name):
    # the interfaces act every 0.05 s (four physics steps): the plan holds there too
    plan = plan_lap(name)
    lap, hits = drive_lap(plan.track, PlanDriver(plan, control_dt=0.05), control_dt=0.05)
    assert hits == 0 and plan.lap_time * (1 - DISCRETISATION) <= lap <= plan.lap_time * (1 + CLOSE)


def test_reference_lap_time_takes_names_seeds_and_tracks_and_remembers(monkeypatch):
    first = reference_lap_time("oval")
    assert reference_lap_time(named_track("oval")) == first
    monkeypatch.setattr(reference, "plan_lap", lambda *a, **k: pytest.fail("planned again"))
    assert reference_lap_time("oval") == first
    monkeypatch.undo()
    seeded = reference_lap("seed-3", centre_line=True)
    assert seeded.track == "seed-3" and seeded.wall_hits == 0 and seeded.driven < seeded.centre_line
    assert reference_lap_time(3) == seeded.driven


def test_drive_lap_gives_up_on_a_driver_that_does_not_drive():
    with pytest.raises(RuntimeError, match="no lap of oval"):
        drive_lap(named_track("oval"), lambda race: np.zeros(3, dtype=np.float32), max_time=5.0)


def test_reference_table_matches_the_docs():
    table = {r.track: r for r in reference.reference_table()}
    assert list(table) == list(TRACK_NAMES)
    text = DOCS.read_text(encoding="utf-8")
    for name, ref in table.items():
        row = re.search(rf"^\| `{name}`[^|]*\| ([\d.]+) s \| ([\d.]+) s \| ([\d.]+) s \|", text, re.MULTILINE)
        assert row, f"docs/simulator.md has no reference row for {name}"
        documented = [float(x) for x in row.groups()]
        assert documented == pytest.approx([ref.planned, ref.driven, ref.centre_line], abs=0.006)


def test_demo_summary_compares_the_best_lap_with_the_reference():
    from tmrl.sim.demo import _versus_reference

    ref = reference_lap_time("oval")
    assert _versus_reference("oval", 2 * ref) == f" = 2.00 x reference {ref:.2f} s"
    assert _versus_reference("nowhere", 30.0) == ""  # no reference: nothing said, nothing broken
