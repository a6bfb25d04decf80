"""The hand-labelled site maps (tests/data/site_labels) and how located sites are scored against them.

    python benchmarks/site_labels.py           # the held-out score table (about 15 s)
    python benchmarks/site_labels.py --loso    # and the leave-one-subject-out study on the training subjects
    python benchmarks/site_labels.py --chain ~/.cache/appliance   # and the maps read through the chain (7 min)
    python benchmarks/site_labels.py --loso --chain ~/.cache/appliance   # and the study on those (20 min)

The labels were given by eye on the middle frame of each PmatData posture file (900 x 1900 mm mat, 10 mm
cells), positions in the body view (along from the head end, across from the patient's right); a spot is
named a site or left unnamed (``None``: a buttock, thigh, calf, hand). Subjects S4, S6 and S11 are the
held-out ones; the others' labels are for fitting.

A labelled spot counts when it is loaded on the monitor's pixels: the map there, within one pixel of it, is at
or above 32 mmHg. The locator's label for it is the site the locator gives the cell (monitor pixel) the spot
lies in (:func:`appliance.alerts.sites.label_cells`; unnamed for a cell below the locator's floor): the label the
monitor gives the tissue there, found without looking at the hand's label. It is right when it equals the hand's
label, unnamed for unnamed included. (Before the locator labelled every cell, the label was the site of the
located spot nearest within 45 mm; a site's second spot, such as a sacrum labelled twice, then counted as
unnamed however the locator read it.)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

LABELS = Path(__file__).resolve().parent.parent / "tests" / "data" / "site_labels"
PMAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "pmatdata"
SECOND_READER = LABELS / "second-reader"
"""Maps labelled again by a second reader, under the same convention, to measure how far two readers agree."""
HELD_OUT = (4, 6, 11)
CONSENSUS = LABELS / "consensus"
"""The held-out subjects' truth: the two readers' agreed labels, each disagreement settled by a third reader from the
map and the convention, blind to the locator (tests/data/site_labels/README.md). One reader's labels agree with
another's on about nine spots in ten, so judging the locator by one reader alone charges it with that reader's
slips."""
MATCH_MM = 45.0
"""How near a true map's peak must lie to a labelled site to be its peak: one and a half 30 mm pixels."""
LOADED_KPA = 32 * 0.133322


@dataclass(frozen=True)
class LabelledSpot:
    subject: int
    posture_file: int
    posture: str
    site: str | None
    along_mm: float
    across_mm: float
    peak_mmhg: float


def label_folder(subject: int) -> Path:
    """Where ``subject``'s labels are read: the consensus for a held-out subject, the first reader's (those the
    locator was fitted on) for a training one."""
    return CONSENSUS if subject in HELD_OUT else LABELS


def labelled_spots(subjects=HELD_OUT) -> list[LabelledSpot]:
    """Every labelled spot of ``subjects``, named or not."""
    spots = []
    for subject in subjects:
        data = json.loads((label_folder(subject) / f"pmatdata-S{subject}.json").read_text(encoding="utf-8"))
        for entry in data["maps"]:
            spots += [LabelledSpot(subject, entry["posture_file"], entry["posture"], s["site"], s["along_mm"],
                                   s["across_mm"], s["peak_mmhg"]) for s in entry["spots"]]
    return spots


def site_positions(spots: list[LabelledSpot], subject: int, posture_file: int) -> dict[str, tuple[float, float]]:
    """Named sites of one labelled map: (along, across) mm; a site labelled twice keeps its higher spot."""
    out: dict[str, tuple[float, float, float]] = {}
    for s in spots:
        if (s.subject == subject and s.posture_file == posture_file and s.site
                and (s.site not in out or s.peak_mmhg > out[s.site][2])):
            out[s.site] = (s.along_mm, s.across_mm, s.peak_mmhg)
    return {site: (a, c) for site, (a, c, _) in out.items()}


def labels_at_spots(true_view, cell_labels: np.ndarray,
                    spots: list[LabelledSpot]) -> list[tuple[str | None, str | None, str]]:
    """(hand label, locator's label, posture) of each labelled spot of one map that is loaded on ``true_view``
    (a :class:`~appliance.alerts.anatomy.BodyView` of the true map on the monitor's pixels); ``cell_labels``:
    the locator's site for each pixel (:func:`~appliance.alerts.sites.label_cells`, on the true map or on a
    map read through the chain)."""
    out = []
    for spot in spots:
        row, col = int(spot.along_mm // true_view.pitch_mm[0]), int(spot.across_mm // true_view.pitch_mm[1])
        if loaded(true_view, spot.along_mm, spot.across_mm):
            out.append((spot.site, cell_labels[row, col], spot.posture))
    return out


def loaded(true_view, along_mm: float, across_mm: float) -> bool:
    """Whether the true map on the monitor's pixels is at or above 32 mmHg within one pixel of a spot."""
    row, col = int(along_mm // true_view.pitch_mm[0]), int(across_mm // true_view.pitch_mm[1])
    return bool(true_view.kpa[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2].max() >= LOADED_KPA)


def reader_pairs(pmat: Path, truth: Path, reader: Path) -> list[tuple[str | None, str | None, str]]:
    """(label in ``truth``, label in ``reader``, posture) of each loaded spot of the maps both folders label, under
    the same convention: the second reader against the first says how far two people agree, the most one reader's
    labels can tell a locator; each reader against the consensus, how far one reader's slips go."""
    from appliance.alerts.site_table_fit import label_maps

    subjects = sorted(int(path.stem.split("-S")[1]) for path in reader.glob("pmatdata-S*.json")
                      if (truth / path.name).exists())
    pairs = []
    for subject in subjects:
        second = json.loads((reader / f"pmatdata-S{subject}.json").read_text(encoding="utf-8"))["maps"]
        for (_, posture, view, spots), entry in zip(label_maps(truth, pmat, [subject]), second, strict=True):
            for first, other in zip(spots, entry["spots"], strict=True):
                if (first["along_mm"], first["across_mm"]) != (other["along_mm"], other["across_mm"]):
                    raise ValueError(f"S{subject} #{entry['posture_file']}: the readers' spots differ")
                if loaded(view, first["along_mm"], first["across_mm"]):
                    pairs.append((first["site"], other["site"], posture))
    return pairs


def score(pairs: list[tuple[str | None, str | None, str]]) -> tuple[int, float, int, float]:
    """(loaded spots, share labelled right, spots named by hand, share of those right)."""
    named = [(hand, found) for hand, found, _ in pairs if hand]
    return (len(pairs), float(np.mean([hand == found for hand, found, _ in pairs])) if pairs else float("nan"),
            len(named), float(np.mean([hand == found for hand, found in named])) if named else float("nan"))


def _labelled(subject: int, posture: str, spots: list[dict]) -> list[LabelledSpot]:
    return [LabelledSpot(subject, 0, posture, s["site"], s["along_mm"], s["across_mm"], s["peak_mmhg"]) for s in spots]


def held_out_pairs(pmat: Path, estimated: bool, truth: Path = CONSENSUS) -> list[tuple[str | None, str | None, str]]:
    """(hand label, locator's label, posture) of every loaded labelled spot of the held-out maps on the true map
    seen by the monitor's pixels; the locator told the posture the maps were recorded in, or (``estimated``) the
    one the shipped posture model reads from the map; the labels in ``truth`` (the consensus, or one reader's)."""
    from appliance.alerts.posture import default_posture_model
    from appliance.alerts.site_table_fit import label_maps
    from appliance.alerts.sites import label_cells

    model = default_posture_model()
    pairs = []
    for subject, posture, view, spots in label_maps(truth, pmat, HELD_OUT):
        told = model.classify(view).posture if estimated else posture
        pairs += labels_at_spots(view, label_cells(view, told), _labelled(subject, posture, spots))
    return pairs


def leave_one_subject_out_pairs(pmat: Path,
                                chain_cache: Path | None = None) -> list[tuple[str | None, str | None, str]]:
    """As :func:`held_out_pairs` (posture recorded) for the training subjects, each map labelled by a table
    fitted on the other training subjects only; with ``chain_cache``, the maps read through the chain are
    labelled (:func:`read_through_chain`), the table still fitted on the true maps as shipped."""
    from appliance.alerts.site_table_fit import TRAINING_SUBJECTS, label_maps
    from appliance.alerts.sites import label_cells

    maps = list(label_maps(LABELS, pmat, TRAINING_SUBJECTS))
    tables = leave_one_out_tables(maps)
    pairs = []
    if chain_cache is None:
        for subject, posture, view, spots in maps:
            pairs += labels_at_spots(view, label_cells(view, posture, table=tables[subject]),
                                     _labelled(subject, posture, spots))
        return pairs
    for true_view, read, labelled in read_through_chain(chain_cache, TRAINING_SUBJECTS):
        subject, posture = labelled[0].subject, labelled[0].posture
        pairs += labels_at_spots(true_view, label_cells(read, posture, table=tables[subject]), labelled)
    return pairs


def leave_one_out_tables(maps) -> dict:
    """For each training subject, the site table fitted on the labelled ``maps`` (subject, posture, view, spots) of
    the other training subjects."""
    from appliance.alerts.site_table import SiteTable
    from appliance.alerts.site_table_fit import TRAINING_SUBJECTS, labelled_points

    points = [(m[0], labelled_points(*m)) for m in maps]
    return {left_out: SiteTable.from_points([p for subject, ps in points if subject != left_out for p in ps])
            for left_out in TRAINING_SUBJECTS}


def read_through_chain(cache: Path, subjects=HELD_OUT):
    """(true view, view read, labelled spots) of every labelled map of ``subjects``: the map read through the whole
    chain (virtual bed, board, reconstruction, calibration; the model cached in ``cache``) as benchmarks/alerts.py
    reads it, and the true map on the monitor's pixels, which says which spots are loaded."""
    from held_out_chain import Chain, true_frame

    from appliance.alerts.anatomy import body_view

    chain, spots = Chain(cache), labelled_spots(subjects)
    for subject in subjects:
        for posture_file in sorted({s.posture_file for s in spots if s.subject == subject}):
            frame = true_frame(subject, posture_file)
            labelled = [s for s in spots if s.subject == subject and s.posture_file == posture_file]
            yield chain.true_view(frame), body_view(chain.read_still(frame), chain.grid), labelled


def chain_pairs(cache: Path) -> list[tuple[str | None, str | None, str]]:
    """As :func:`held_out_pairs` (posture estimated) for the held-out maps read through the chain
    (:func:`read_through_chain`)."""
    from appliance.alerts.posture import default_posture_model
    from appliance.alerts.sites import label_cells

    model = default_posture_model()
    return [pair for true_view, read, labelled in read_through_chain(cache)
            for pair in labels_at_spots(true_view, label_cells(read, model.classify(read).posture), labelled)]


def main(argv=None) -> None:
    """Print the held-out score table (true maps on the monitor's 30 mm pixels), and with ``--loso`` the
    leave-one-subject-out study over the training subjects; written to benchmarks/site_labels.md too."""
    import argparse
    from collections import Counter

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pmat", type=Path, default=PMAT, help="the PmatData folder the labels were given on")
    parser.add_argument("--loso", action="store_true",
                        help="also the leave-one-subject-out study on the training subjects")
    parser.add_argument("--chain", type=Path, metavar="MODEL_CACHE",
                        help="also the maps read through the whole chain, with the model cached in this folder")
    args = parser.parse_args(argv)
    runs = [("held-out S4, S6, S11; posture recorded", lambda: held_out_pairs(args.pmat, False)),
            ("held-out S4, S6, S11; posture estimated", lambda: held_out_pairs(args.pmat, True))]
    if args.chain:
        runs.append(("held-out, read through the chain; posture estimated", lambda: chain_pairs(args.chain)))
    if args.loso:
        runs.insert(0, ("training, leave one subject out; posture recorded",
                        lambda: leave_one_subject_out_pairs(args.pmat)))
    runs += [("a second reader against the first (S1, S4, S6, S11)",
              lambda: reader_pairs(args.pmat, LABELS, SECOND_READER)),
             ("the first reader against the consensus (S1, S4, S6, S11)",
              lambda: reader_pairs(args.pmat, CONSENSUS, LABELS)),
             ("the second reader against the consensus (S1, S4, S6, S11)",
              lambda: reader_pairs(args.pmat, CONSENSUS, SECOND_READER)),
             ("held-out S4, S6, S11 against the first reader alone; posture estimated",
              lambda: held_out_pairs(args.pmat, True, LABELS))]
    if args.loso and args.chain:
        runs.insert(1, ("training, leave one subject out, read through the chain; posture recorded",
                        lambda: leave_one_subject_out_pairs(args.pmat, args.chain)))
    from report import machine                  # beside this script when it runs as one

    command = "python benchmarks/site_labels.py" + "".join(f" {a}" for a in (argv if argv is not None else
                                                                            __import__("sys").argv[1:]))
    lines = ["# Site labels against the hand labels", "",
             f"Made by `{command}` on {machine()}.",
             "A loaded labelled spot is right when the locator's label for its monitor pixel is the hand's (unnamed "
             "for unnamed included). Every subject was labelled under one written convention "
             "(tests/data/site_labels/CONVENTION.md); four subjects were labelled again by a second reader, and "
             "their disagreements settled by a third, blind to the locator: the held-out subjects are judged "
             "against that consensus. The last rows score the readers against each other and against the "
             "consensus (the agreement people reach), and the locator against the first reader alone.", "",
             "| maps | loaded spots | labelled right | named by hand | of those, right |", "|---|---|---|---|---|"]
    wrong: dict[str, Counter] = {}
    for name, run in runs:
        pairs = run()
        n, right, n_named, named_right = score(pairs)
        lines.append(f"| {name} | {n} | {right:.1%} | {n_named} | {named_right:.1%} |")
        wrong[name] = Counter((hand, found) for hand, found, _ in pairs if hand != found)
    for name, counts in wrong.items():
        lines += ["", f"Disagreements, {name}: " + "; ".join(
            f"{n} x {b or 'unnamed'} where the labels say {a or 'unnamed'}" for (a, b), n in counts.most_common(8))]
    text = "\n".join(lines) + "\n"
    print(text)
    (Path(__file__).parent / "site_labels.md").write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
