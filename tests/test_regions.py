"""Region tracking: stable ids under drift, split and merge, restart (regions are what the screen draws;
alarms are per tissue site)."""

import json

import numpy as np
import pytest

from appliance.alerts.regions import RegionTracker
from appliance.core.named_layouts import get_layout
from appliance.core.pixels import pixel_grid
from appliance.core.pressure_map import PressureMap

BED = pixel_grid(get_layout("grid-8x16"), 16, 34)  # 16 x 34 pixels of ~56 mm, 1900 x 900 mm
SMALL = pixel_grid(get_layout("grid-4x4"))         # 16 x 16 pixels of 6.25 mm, 100 x 100 mm


def frame(t, kpa):
    return PressureMap(float(t), kpa, [], None, 0)


def blobs(grid, *boxes, kpa=6.0):
    """A map with rectangles (r0, r1, c0, c1) of ``kpa``."""
    p = np.zeros(grid.shape)
    for r0, r1, c0, c1 in boxes:
        p[r0:r1, c0:c1] = kpa
    return p


def ids(regions):
    return sorted(r.id for r in regions)


def by_column(regions):
    return sorted(regions, key=lambda r: r.x_mm)


def test_a_region_drifting_a_few_cm_keeps_its_id():
    tracker = RegionTracker(SMALL)
    first = tracker.update(frame(0, blobs(SMALL, (4, 8, 4, 8))))
    for t, shift in enumerate([1, 2, 3, 4, 5, 6], start=1):     # 6.25 mm a frame, overlapping
        regions = tracker.update(frame(t, blobs(SMALL, (4, 8, 4 + shift, 8 + shift))))
    assert ids(first) == ids(regions) == [1]
    assert regions[0].first_seen_s == 0.0


def test_a_one_pixel_heel_stepping_to_the_next_pixel_keeps_its_id():
    tracker = RegionTracker(BED)
    tracker.update(frame(0, blobs(BED, (6, 7, 31, 32))))
    regions = tracker.update(frame(1, blobs(BED, (7, 8, 31, 32))))       # 56 mm, no overlap
    assert ids(regions) == [1]


def test_a_region_appearing_far_away_gets_a_new_id():
    tracker = RegionTracker(BED)
    tracker.update(frame(0, blobs(BED, (7, 9, 3, 4))))
    regions = tracker.update(frame(1, blobs(BED, (7, 9, 3, 4), (6, 7, 31, 32))))
    assert [r.id for r in by_column(regions)] == [1, 2]
    assert by_column(regions)[1].first_seen_s == 1.0


def test_a_jump_beyond_max_jump_is_a_new_region():
    tracker = RegionTracker(BED)
    tracker.update(frame(0, blobs(BED, (6, 7, 31, 32))))
    assert ids(tracker.update(frame(1, blobs(BED, (6, 7, 29, 30))))) == [2]    # 112 mm


def test_a_split_keeps_the_id_on_the_largest_child():
    tracker = RegionTracker(SMALL)
    tracker.update(frame(0, blobs(SMALL, (4, 8, 2, 14))))
    regions = by_column(tracker.update(frame(5, blobs(SMALL, (4, 8, 2, 5), (4, 8, 6, 14)))))
    assert [r.id for r in regions] == [2, 1]
    assert [r.split_from for r in regions] == [1, None]
    assert [r.first_seen_s for r in regions] == [0.0, 0.0]      # the child's tissue was loaded all along
    assert [r.split_from for r in tracker.update(frame(6, blobs(SMALL, (4, 8, 2, 5), (4, 8, 6, 14))))] == \
        [None, None]


def test_a_merge_keeps_the_oldest_id_and_lists_the_absorbed():
    tracker = RegionTracker(SMALL)
    tracker.update(frame(0, blobs(SMALL, (4, 8, 2, 5))))
    tracker.update(frame(1, blobs(SMALL, (4, 8, 2, 5), (4, 8, 9, 14))))       # a larger, younger one
    regions = tracker.update(frame(2, blobs(SMALL, (4, 8, 2, 14))))
    assert [(r.id, r.merged, r.first_seen_s) for r in regions] == [(1, (2,), 0.0)]


def test_regions_below_the_minimum_area_are_dropped():
    kpa = blobs(SMALL, (1, 2, 1, 2), (6, 10, 6, 10))          # 1 pixel (0.39 cm2) and 16 (6.25 cm2)
    assert len(RegionTracker(SMALL).update(frame(0, kpa))) == 2     # default: one pixel keeps all
    regions = RegionTracker(SMALL, min_area_cm2=1.0).update(frame(0, kpa))
    assert [r.area_cm2 for r in regions] == [6.25]


def test_the_default_keeps_a_one_pixel_heel_on_the_bed():
    assert [r.area_cm2 for r in RegionTracker(BED).update(frame(0, blobs(BED, (6, 7, 31, 32))))] == \
        [pytest.approx(BED.pixel_mm[0] * BED.pixel_mm[1] / 100)]


def test_ids_are_never_reused():
    tracker = RegionTracker(BED)
    seen = []
    for t in range(6):
        kpa = blobs(BED, (6, 7, 31, 32)) if t % 2 == 0 else np.zeros(BED.shape)   # on, off, on ...
        seen += [r.id for r in tracker.update(frame(t, kpa))]
    assert seen == [1, 2, 3]


def test_state_round_trip_gives_the_same_ids():
    frames = [blobs(BED, (6, 8, 3, 4), (6, 7, 31, 32)), blobs(BED, (7, 9, 3, 4), (7, 8, 31, 32)),
              blobs(BED, (7, 9, 3, 4), (7, 8, 31, 32), (2, 3, 15, 16)),
              blobs(BED, (7, 9, 3, 5), (2, 4, 15, 16)), blobs(BED, (2, 4, 15, 16), (12, 13, 20, 21))]
    tracker = RegionTracker(BED)
    for t, kpa in enumerate(frames[:2]):
        tracker.update(frame(t, kpa))
    restored = RegionTracker.from_state(BED, json.loads(json.dumps(tracker.state())))
    for t, kpa in enumerate(frames[2:], start=2):
        a, b = tracker.update(frame(t, kpa)), restored.update(frame(t, kpa))
        assert [(r.id, r.first_seen_s, r.split_from, r.merged, r.zone) for r in a] == \
               [(r.id, r.first_seen_s, r.split_from, r.merged, r.zone) for r in b]
    assert restored.next_id == tracker.next_id == 5


def test_state_of_another_grid_is_refused():
    with pytest.raises(ValueError):
        RegionTracker.from_state(SMALL, RegionTracker(BED).state())
