"""The site locator names the bony prominence under each loaded spot, wherever the body lies on the mat."""

import functools
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from appliance.alerts.anatomy import BodyView, posture_side
from appliance.alerts.site_table import LabelledPoint, SiteTable
from appliance.alerts.sites import FLOOR_KPA, TROCHANTER_REACH_MM, SiteReading, label_cells, locate_sites
from appliance.errors import ConfigError, ModelInputInvalid
from appliance.sim.body import MatGrid, Placement, Subject, body_field, body_patches
from appliance.sim.field import KPA_PER_MMHG
from appliance.sim.recordings import pmat_scene, resample_onto

MONITOR_CELLS = MatGrid(900.0, 1900.0, 1900.0 / 64)
PITCH = (1900.0 / 64, 900.0 / 30)
PMAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "pmatdata"
TRAINING = (1, 2, 3, 5, 7, 8, 9, 10)          # S4, S6 and S11 are held out for validating the product
LOCATOR_POSTURE = {"supine": "supine", "left-30": "left-30", "right-30": "right-30",
                   "head-raised-30": "inclined", "head-raised-45": "inclined"}
MUST_FIND = {"supine": {"occiput", "sacrum", "heel-left", "heel-right"},
             "left-30": {"occiput"}, "right-30": {"occiput"},
             "head-raised-30": {"sacrum", "heel-left", "heel-right"},
             "head-raised-45": {"sacrum", "heel-left", "heel-right"}}


def monitor_view(kpa_10mm: np.ndarray, blurred: bool = True) -> BodyView:
    """A 10 mm map as the monitor sees it: 30 mm cells and, if ``blurred``, spread by about a pixel as a
    reconstruction spreads it."""
    cells = resample_onto(kpa_10mm, 10.0, MONITOR_CELLS)
    return BodyView(gaussian_filter(cells, 0.5) if blurred else cells, PITCH, True)


def true_sites_mm(subject, placement, posture_name):
    """Each patch's centre in view mm (along, across); the raised head of bed loads the buttocks' ischia."""
    t = math.radians(placement.rotation_deg)
    out = {}
    for p in body_patches(subject, placement.posture):
        site = p.site.replace("buttock", "ischium") if posture_name == "inclined" else p.site
        out[site] = (placement.y_mm + p.s * math.cos(t) - p.u * math.sin(t),
                     placement.x_mm + p.s * math.sin(t) + p.u * math.cos(t))
    return out


def named(readings):
    return {r.site: r for r in readings if r.site}


@pytest.mark.parametrize("posture", sorted(LOCATOR_POSTURE))
@pytest.mark.parametrize("across_mm, slid_mm, turn_deg, blurred", [
    (450, 0, 0, False), (450, 0, 0, True), (350, 150, 5, True), (550, 100, -5, True), (500, 0, -4, False)])
def test_virtual_body_sites_found_where_they_lie(posture, across_mm, slid_mm, turn_deg, blurred):
    subject = Subject(75.0, 170.0)
    placement = Placement(posture, across_mm, (1900 - 1700) / 2 - 50 + slid_mm, turn_deg)
    view = monitor_view(body_field(subject, placement).pressure_kpa, blurred)
    truth = true_sites_mm(subject, placement, LOCATOR_POSTURE[posture])
    readings = locate_sites(view, LOCATOR_POSTURE[posture])
    sites = named(readings)
    assert MUST_FIND[posture] <= set(sites), f"missing {MUST_FIND[posture] - set(sites)}"
    if posture in ("left-30", "right-30"):
        # The hand labels read a 30-degree tilt as clinicians do (tests/data/site_labels/README.md): the loaded
        # down-side shoulder blade is the scapula, the gluteal spot no site, the lone heel the upper leg's. The
        # virtual body names them shoulder, trochanter and the down heel, so only where they lie is compared.
        down = posture.split("-")[0]
        blade = [sites[s] for s in (f"scapula-{down}", f"shoulder-{down}") if s in sites]
        assert blade and min(math.hypot(blade[0].along_mm - a, blade[0].across_mm - c) for a, c in
                             (truth[f"scapula-{down}"], truth[f"shoulder-{down}"])) < 60.0
        sites = {s: sites[s] for s in MUST_FIND[posture]}
    if LOCATOR_POSTURE[posture] == "inclined":
        # The hand labels put the ischia 7-9 cm either side of the sacral peak and 5-10 cm below it; the virtual
        # body's buttock patches lie 11 cm out: an ischium is checked to lie below the sacrum, on its own side.
        for side, sign in (("left", 1), ("right", -1)):
            if f"ischium-{side}" in sites:
                ischium, sacrum = sites.pop(f"ischium-{side}"), sites["sacrum"]
                assert 0.0 < ischium.along_mm - sacrum.along_mm < 150.0
                assert 20.0 < sign * (ischium.across_mm - sacrum.across_mm) < 120.0
    for site, r in sites.items():
        along, across = truth[site]
        assert math.hypot(r.along_mm - along, r.across_mm - across) < 60.0, site
    assert all(r.peak_kpa >= 20 * KPA_PER_MMHG for r in readings)


def test_each_site_names_one_spot_at_most_and_others_stay_in_the_result():
    view = monitor_view(body_field(Subject(75.0, 175.0), Placement("supine")).pressure_kpa)
    readings = locate_sites(view, "supine", floor_kpa=10 * KPA_PER_MMHG)
    names = [r.site for r in readings if r.site]
    assert len(names) == len(set(names))
    assert any(r.site is None for r in readings)           # buttocks and calves: loaded, no bony prominence
    assert [r.peak_kpa for r in readings] == sorted((r.peak_kpa for r in readings), reverse=True)


def test_a_patient_slid_towards_the_foot_keeps_the_labels():
    subject = Subject(70.0, 165.0)
    def labels(head_mm):
        view = monitor_view(body_field(subject, Placement("supine", 450, head_mm)).pressure_kpa)
        return {r.site: r.along_mm for r in locate_sites(view, "supine") if r.site}
    at_head, slid = labels(30.0), labels(230.0)
    assert set(at_head) == set(slid) >= {"occiput", "sacrum", "heel-left", "heel-right"}
    for site in at_head:
        assert slid[site] - at_head[site] == pytest.approx(200.0, abs=30.0), site


def test_left_and_right_follow_the_patient_not_the_mat():
    subject = Subject(75.0, 175.0)
    for posture, down in (("left-30", "left"), ("right-30", "right")):
        view = monitor_view(body_field(subject, Placement(posture)).pressure_kpa)
        sites = named(locate_sites(view, posture))
        assert f"scapula-{down}" in sites or f"shoulder-{down}" in sites
        assert not any(s.endswith("left" if down == "right" else "right") and s.startswith(("trochanter", "shoulder"))
                       for s in sites)


def one_lower_leg(view: BodyView, kept: str) -> BodyView:
    """``view`` with the other leg lifted off the mat from the knee down (as with the legs crossed or one knee up):
    the cells below 60 % of the contact's length on the patient's other side of the gap between the lower legs."""
    kpa = view.kpa.copy()
    rows = np.flatnonzero((kpa >= 5 * KPA_PER_MMHG).any(axis=1))
    knee = rows[0] + int(0.6 * (rows[-1] - rows[0]))
    legs = (kpa[knee:] > 0.3).any(axis=0)
    first, last = np.flatnonzero(legs)[[0, -1]]
    gap = np.flatnonzero(~legs[first:last + 1]) + first
    middle = int(gap[len(gap) // 2])
    if kept == "right":
        kpa[knee:, middle:] = 0.0
    else:
        kpa[knee:, :middle + 1] = 0.0
    return BodyView(kpa, view.pitch_mm, view.transposed)


@pytest.mark.parametrize("subject, across_mm", [(Subject(75.0, 175.0), 450.0), (Subject(60.0, 160.0), 400.0)])
@pytest.mark.parametrize("posture", ["supine", "left-30", "right-30"])
@pytest.mark.parametrize("kept", ["left", "right"])
def test_a_heel_alone_on_the_mat_is_named_by_the_side_of_the_trunk_it_lies_on(subject, across_mm, posture, kept):
    """The legs' own midline runs through a lone heel; the trunk's does not. Tilted 30 degrees the heels are named
    as lying on the back (the convention says so)."""
    view = one_lower_leg(monitor_view(body_field(subject, Placement(posture, across_mm)).pressure_kpa), kept)
    names = label_cells(view, posture, floor_kpa=12 * KPA_PER_MMHG)
    assert {n for n in names.ravel() if n and n.startswith("heel")} == {f"heel-{kept}"}


def test_sitting_on_the_edge_names_the_ischia_by_the_way_the_patient_faces():
    kpa = np.zeros((64, 30))
    kpa[30, 2], kpa[34, 2] = 12.0, 10.0                    # on the right-hand edge, facing out: left to the foot
    sites = named(locate_sites(BodyView(kpa, PITCH, True), "sitting-edge"))
    assert sites["ischium-right"].along_mm < sites["ischium-left"].along_mm
    far_edge = named(locate_sites(BodyView(kpa[:, ::-1].copy(), PITCH, True), "sitting-edge"))
    assert far_edge["ischium-right"].along_mm > far_edge["ischium-left"].along_mm


def test_out_of_bed_an_empty_map_and_bad_input():
    view = monitor_view(body_field().pressure_kpa)
    assert locate_sites(view, "out-of-bed") == []
    assert locate_sites(BodyView(np.zeros((64, 30)), PITCH, True), "supine") == []
    with pytest.raises(ConfigError, match="unknown posture 'lying'"):
        locate_sites(view, "lying")
    with pytest.raises(ModelInputInvalid, match="2-D"):
        locate_sites(BodyView(np.zeros(64 * 30), PITCH, True), "supine")
    with pytest.raises(ModelInputInvalid, match="no bed"):
        locate_sites(BodyView(np.zeros((10, 10)), (10.0, 10.0), True), "supine")
    with pytest.raises(ModelInputInvalid, match="non-finite"):
        locate_sites(BodyView(np.full((64, 30), np.nan), PITCH, True), "supine")
    assert SiteReading("sacrum", 1.0, 2.0, 3.0) == SiteReading("sacrum", 1.0, 2.0, 3.0)


def little_contact(shape: str) -> np.ndarray:
    """A bed map holding no whole body: what the mat reads while a patient gets in or out, or a foot alone."""
    kpa = np.zeros((64, 30))
    if shape == "one row":
        kpa[30, 10:14] = 8.0
    elif shape == "one blob":
        kpa[30:33, 10:13] = 8.0
    elif shape == "the feet only":
        kpa[60:64, 5:25] = 8.0
    elif shape == "two specks":
        kpa[10:12, 3] = kpa[50:52, 25] = 9.0
    elif shape == "a lone hot cell":
        kpa[40, 12] = 12.0
    elif shape == "a stripe":
        kpa[:, 14:16] = 8.0
    elif shape == "all loaded":
        kpa[:] = 8.0
    else:
        kpa[:] = np.random.default_rng(0).uniform(0.0, 10.0, kpa.shape)
    return kpa


@pytest.mark.parametrize("shape", ["one row", "one blob", "the feet only", "two specks", "a lone hot cell",
                                   "a stripe", "all loaded", "noise"])
@pytest.mark.parametrize("posture", ["supine", "inclined", "left-30", "right-60", "left-90", "fetal-right", "prone",
                                     "sitting-edge"])
def test_a_map_holding_no_whole_body_is_labelled_without_error(shape, posture):
    """The monitor keeps the last sure lying posture through unsure maps, so the locator meets such maps in any
    posture; it names some of their loaded cells or none, and never fails."""
    view = BodyView(little_contact(shape), PITCH, True)
    names = label_cells(view, posture)
    assert names.shape == view.shape
    assert all(name is None for name in names[view.kpa < FLOOR_KPA])
    assert {r.site for r in locate_sites(view, posture)} <= set(names.ravel())


def test_random_maps_are_labelled_in_every_posture_without_error():
    """Blocks of load of any size anywhere, on a quiet or a noisy mat: whatever the posture, the locator names
    loaded cells or none, and never fails."""
    from appliance.alerts.anatomy import POSTURES
    rng = np.random.default_rng(1)
    for _ in range(150):
        kpa = np.zeros((64, 30))
        for _ in range(rng.integers(1, 6)):
            r, c, h, w = rng.integers(0, 64), rng.integers(0, 30), rng.integers(1, 20), rng.integers(1, 12)
            kpa[r:r + h, c:c + w] = rng.uniform(0.5, 20.0)
        if rng.random() < 0.3:
            kpa += rng.uniform(0.0, 3.0, kpa.shape)
        view = BodyView(kpa, PITCH, True)
        for posture in POSTURES:
            names = label_cells(view, posture)
            assert all(name is None for name in names[kpa < FLOOR_KPA])


needs_pmat = pytest.mark.skipif(not PMAT.is_dir(), reason="PmatData is not on this machine")


@functools.cache
def pmat_view(subject: int, posture_file: int) -> BodyView:
    scene = pmat_scene(PMAT, subject, posture_file, MatGrid(900.0, 1900.0, 10.0))
    return monitor_view(scene.frames[len(scene.frames) // 2], blurred=False)


@needs_pmat
@pytest.mark.parametrize("subject", TRAINING)
def test_training_subjects_supine_order_and_sides(subject):
    # the 28.5 mm sensels spread a heel over two 30 mm cells: PmatData's heels read 12-25 mmHg
    sites = named(locate_sites(pmat_view(subject, 1), "supine", floor_kpa=12 * KPA_PER_MMHG))
    assert {"occiput", "sacrum"} <= set(sites)
    heels = [sites[h] for h in ("heel-left", "heel-right") if h in sites]
    assert all(sites["occiput"].along_mm < sites["sacrum"].along_mm < h.along_mm for h in heels)
    if len(heels) == 2:
        assert sites["heel-left"].across_mm > sites["heel-right"].across_mm
    for pair in ("scapula", "elbow"):
        if f"{pair}-left" in sites and f"{pair}-right" in sites:
            assert sites[f"{pair}-left"].across_mm > sites[f"{pair}-right"].across_mm


@needs_pmat
def test_training_subjects_heels_are_mostly_found():
    """S8's heels lie at 0.88 of the fitted length, among the calves: one miss in eight is the known rate."""
    found = sum(any(r.site and r.site.startswith("heel") for r in
                    locate_sites(pmat_view(s, 1), "supine", floor_kpa=12 * KPA_PER_MMHG)) for s in TRAINING)
    assert found >= 7


@needs_pmat
@pytest.mark.parametrize("subject", TRAINING)
@pytest.mark.parametrize("posture_file, posture, down", [(2, "right-90", "right"), (3, "left-90", "left")])
def test_training_subjects_side_lying_rest_on_the_down_side(subject, posture_file, posture, down):
    sites = named(locate_sites(pmat_view(subject, posture_file), posture))
    assert f"trochanter-{down}" in sites
    up = "left" if down == "right" else "right"
    assert not any(s in sites for s in (f"trochanter-{up}", f"shoulder-{up}", f"ear-{up}"))
    if f"shoulder-{down}" in sites:
        assert sites[f"shoulder-{down}"].along_mm < sites[f"trochanter-{down}"].along_mm


@needs_pmat
def test_the_sites_come_from_the_table_given():
    """A study of the training subjects locates each one's sites with a table fitted without them: the table
    passed is the one voting (one that names nothing leaves a side-lying body with no site)."""
    view = pmat_view(1, 3)
    nameless = SiteTable.from_points([LabelledPoint(0, "left-90", 0.5, 0.0, 1.0, None)])
    assert "trochanter-left" in named(locate_sites(view, "left-90"))
    assert named(locate_sites(view, "left-90", table=nameless)) == {}


@needs_pmat
@pytest.mark.parametrize("subject", TRAINING)
@pytest.mark.parametrize("posture_file, posture", [(2, "right-90"), (3, "left-90"), (13, "fetal-right"),
                                                   (14, "fetal-left")])
def test_a_side_lying_trochanter_is_its_hot_spot_and_the_hip_within_reach_of_it(subject, posture_file, posture):
    view = pmat_view(subject, posture_file)
    names = label_cells(view, posture)
    site = f"trochanter-{posture_side(posture)}"
    cells = [tuple(rc) for rc in np.argwhere(names == site)]
    assert cells
    loaded = [tuple(rc) for rc in np.argwhere(view.kpa >= FLOOR_KPA)]

    def reach(peak):
        return {rc for rc in loaded if names[rc] in (None, site)
                and math.dist(view.cell_centre_mm(*rc), view.cell_centre_mm(*peak)) <= TROCHANTER_REACH_MM}
    # some cell of it (its peak before the hip around it joined) reaches exactly the trochanter's cells
    assert any(reach(peak) == set(cells) for peak in cells)


# ---------------------------------------------------------------------------
# The learned table, on the training subjects' labels (S4, S6 and S11 are held out and never read here)

LABELS = Path(__file__).resolve().parent / "data" / "site_labels"
LOSO_ALL, LOSO_NAMED, LOSO_MARGIN = 0.854, 0.817, 0.02
"""Leave-one-subject-out accuracy measured on the loaded labelled spots (all, and those the hand named) when the
locator's constants were chosen (``python benchmarks/site_labels.py --loso``). The margin allows for small changes
to the frame fit; the locator with the earlier trochanter reach of 75 mm gave 0.790 (0.805 of the named), and before
it named the back by the convention's landmarks and gathered shoulders (sites.py ``_name_the_back``,
``_gather_at_hot_spots``) 0.800 (0.797), before the head was told from a raised arm (landmarks.py) and a hot iliac
crest from the trochanter (sites.py ``_below_the_iliac_crest``) 0.824 (0.793), and before the occiput was what
lies within reach of the head's peak 0.831 (0.797), and before a streak was kept from weighing the pelvis
(landmarks.py ``STREAK_CELLS``) 0.850 (0.819)."""


@pytest.fixture(scope="module")
def training_maps():
    """(subject, posture, view, spots) of every labelled training map, loaded once."""
    from appliance.alerts.site_table_fit import TRAINING_SUBJECTS, label_maps
    return list(label_maps(LABELS, PMAT, TRAINING_SUBJECTS))


@needs_pmat
@pytest.mark.parametrize("posture, crest_mm, root_mm", [("left-90", (745, 405), (875, 385)),
                                                       ("fetal-left", (845, 375), (975, 405))])
def test_a_hip_hot_on_its_iliac_crest_has_the_trochanter_at_the_thigh_root(posture, crest_mm, root_mm):
    """Subject 8's hip is hottest 130 mm above the thigh root (the readers' notes: 'by rule the iliac crest'); the
    trochanter is the spot at the thigh root, as the convention says, and the crest no site."""
    from appliance.alerts.site_table_fit import label_maps
    view = next(v for _, p, v, _ in label_maps(LABELS, PMAT, [8]) if p == posture)
    names = label_cells(view, posture)

    def name_at(along, across):
        return names[int(along // view.pitch_mm[0]), int(across // view.pitch_mm[1])]
    assert name_at(*root_mm) == "trochanter-left"
    assert name_at(*crest_mm) is None


@needs_pmat
def test_a_side_lying_shoulder_blade_lies_apart_from_the_shoulder(training_maps):
    """The convention names the shoulder first (all within 85 mm of its hottest cell) and a blade only 90 mm or more
    below that peak, so no cell of the down side's blade touches the shoulder's (37 did when the table's blade was
    kept within the shoulder's reach)."""
    touching, blades = 0, 0
    for _, posture, view, _ in training_maps:
        if posture_side(posture) is None or posture.endswith("30"):
            continue
        names = label_cells(view, posture)
        down = posture_side(posture)
        shoulder = np.argwhere(names == f"shoulder-{down}")
        for r, c in np.argwhere(names == f"scapula-{down}"):
            blades += 1
            touching += any(abs(r - a) <= 1 and abs(c - b) <= 1 for a, b in shoulder)
    assert blades > 0
    assert touching == 0


@needs_pmat
def test_the_fit_script_rebuilds_the_shipped_table(tmp_path):
    from appliance.alerts.site_table import TABLE_PATH
    from appliance.alerts.site_table_fit import main
    main(["--fit", str(LABELS), "--pmat", str(PMAT), "--out", str(tmp_path / "table.json")])
    assert (tmp_path / "table.json").read_bytes() == TABLE_PATH.read_bytes()


@needs_pmat
def test_leave_one_subject_out_accuracy_holds(training_maps):
    from appliance.alerts.site_table import SiteTable
    from appliance.alerts.site_table_fit import labelled_points
    points = [(m[0], labelled_points(*m)) for m in training_maps]
    tables = {subject: SiteTable.from_points([p for s, ps in points if s != subject for p in ps])
              for subject in TRAINING}
    right = []
    for subject, posture, view, spots in training_maps:
        cells = label_cells(view, posture, table=tables[subject])
        for spot in spots:
            r, c = int(spot["along_mm"] // view.pitch_mm[0]), int(spot["across_mm"] // view.pitch_mm[1])
            if view.kpa[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2].max() >= 32 * KPA_PER_MMHG:
                right.append((spot["site"], cells[r, c] == spot["site"]))
    assert np.mean([ok for _, ok in right]) >= LOSO_ALL - LOSO_MARGIN
    assert np.mean([ok for site, ok in right if site]) >= LOSO_NAMED - LOSO_MARGIN


@needs_pmat
@pytest.mark.parametrize("posture_file, posture", [(1, "supine"), (3, "left-90"), (15, "inclined")])
def test_labels_follow_a_real_body_slid_along_and_across(posture_file, posture):
    """The same subject moved 60 mm across and 50 mm down the mat keeps its sites, each moved by as much.
    PmatData's body fills 1.8 m of the 1.9 m mat, so a longer slide puts the feet off it (the virtual body
    checks 200 mm above); sites peaking near the 20 mmHg floor may drop out as the pixels cut them anew."""
    def sites(shift_mm):
        scene = pmat_scene(PMAT, 1, posture_file, MatGrid(900.0, 1900.0, 10.0), shift_mm=shift_mm)
        return named(locate_sites(monitor_view(scene.frames[len(scene.frames) // 2], blurred=False), posture))
    still, slid = sites((0.0, 0.0)), sites((60.0, 50.0))
    clear = {site for site, r in still.items() if r.peak_kpa >= 25 * KPA_PER_MMHG}
    assert clear and clear <= set(slid)
    for site in clear:
        assert math.hypot(slid[site].along_mm - still[site].along_mm - 50.0,
                          slid[site].across_mm - still[site].across_mm - 60.0) < 45.0, site


# ---------------------------------------------------------------------------
# The shipped locator on the held-out subjects' labels (S4, S6, S11): read to judge it, never to fit it

HELD_OUT_RIGHT = {False: (0.860, 0.844), True: (0.836, 0.809)}
"""Share of the loaded held-out spots labelled right (all, and those the hand named) against the consensus labels,
the locator told the posture recorded (False) or the posture model's estimate (True), as measured by
``python benchmarks/site_labels.py``."""
HELD_OUT_MARGIN = 0.015


@needs_pmat
@pytest.mark.parametrize("estimated", [False, True])
def test_the_shipped_locator_holds_its_held_out_score(estimated):
    import importlib.util
    import sys
    path = Path(__file__).resolve().parent.parent / "benchmarks" / "site_labels.py"
    spec = importlib.util.spec_from_file_location("bench_site_labels", path)
    bench = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = bench              # its dataclasses look themselves up there
    spec.loader.exec_module(bench)
    n, right, n_named, named_right = bench.score(bench.held_out_pairs(PMAT, estimated))
    assert (n, n_named) == (371, 199)           # the loaded spots: fixed by the true maps and the consensus labels
    assert right >= HELD_OUT_RIGHT[estimated][0] - HELD_OUT_MARGIN
    assert named_right >= HELD_OUT_RIGHT[estimated][1] - HELD_OUT_MARGIN
