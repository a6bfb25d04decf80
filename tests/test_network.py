"""The thesis's resistor network: its worked example, its phantoms, its own procedure."""

import numpy as np
import pytest

from appliance.core.forward import simulate, solve_electrodes
from appliance.core.named_layouts import get_layout
from appliance.core.network import (
    ELEMENT_MATRIX, NetworkGrid, appendix_b_electrode_volts, build_network_model, conductance_matrix,
    network_for_layout, thesis_phantom,
)
from appliance.core.protocols import default_protocol
from appliance.errors import LayoutInvalid

# G_sys of the thesis's 4-element example (section 5.4, Fig. 5.4.5), as printed.
THESIS_GSYS = np.array([
    [3, -1, 0, -1, -1, 0, 0, 0, 0],
    [-1, 6, -1, -1, -2, -1, 0, 0, 0],
    [0, -1, 3, 0, -1, -1, 0, 0, 0],
    [-1, -1, 0, 6, -2, 0, -1, 0, 0],
    [-1, -2, -1, -2, 12, -2, -1, -1, -1],
    [0, -1, -1, 0, -2, 6, 0, -2, -1],
    [0, 0, 0, -1, -1, 0, 3, -1, 0],
    [0, 0, 0, -1, -2, -1, -1, 6, -1],
    [0, 0, 0, 0, -1, -1, 0, -1, 3],
])


def test_element_matrix_is_g_ele():
    assert np.array_equal(ELEMENT_MATRIX, [[3, -1, -1, -1], [-1, 3, -1, -1], [-1, -1, 3, -1], [-1, -1, -1, 3]])


def test_worked_example_reproduces_the_printed_system_matrix():
    """The printed column 8 is shifted down one row in rows 4 to 6 (it reads 0, -1, -2
    where row 8, its symmetric partner, reads -1, -2, -1), so those three rows do not
    sum to zero as Kirchhoff's law requires; every other entry matches exactly."""
    grid = NetworkGrid(np.ones((2, 2), dtype=bool), 1.0, ((0,), (3,)))
    assert grid.topology.tolist() == [[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6], [4, 5, 8, 7]]  # Table 5.4.1
    ours = conductance_matrix(grid, np.ones(4)).toarray()
    slips = {(3, 7), (4, 7), (5, 7)}
    for (i, j), value in np.ndenumerate(THESIS_GSYS):
        if (i, j) not in slips:
            assert ours[i, j] == value, (i + 1, j + 1)
    assert np.array_equal(ours[3:6, 7], THESIS_GSYS[7, 3:6])
    assert np.allclose(ours.sum(axis=1), 0)
    assert np.flatnonzero(THESIS_GSYS.sum(axis=1)).tolist() == [3, 4, 5]


@pytest.mark.parametrize(("letter", "cells", "nodes", "electrode_elements"), [
    ("A", 241, 276, [4, 7, 31, 78, 129, 180, 223, 241, 238, 235, 211, 164, 113, 62, 19, 1]),
    ("B", 289, 324, [1, 5, 9, 13, 17, 85, 153, 221, 289, 285, 281, 277, 273, 205, 137, 69]),
    ("C", 256, 289, [1, 6, 11, 16, 81, 86, 91, 96, 161, 166, 171, 176, 241, 246, 251, 256]),
])
def test_phantoms_match_appendix_b(letter, cells, nodes, electrode_elements):
    grid = thesis_phantom(letter)
    assert grid.n_cells == cells and grid.n_nodes == nodes
    assert [c[0] + 1 for c in grid.electrode_cells] == electrode_elements
    if letter == "B":
        assert (grid.topology[0] + 1).tolist() == [1, 2, 20, 19]    # A = [1 2 20 19] in Appendix B
    if letter == "C":
        assert (grid.topology[0] + 1).tolist() == [1, 2, 19, 18]
    if letter == "A":   # the printed 13 x 13 anomaly rows 19:31, 33:45, ... sit in rows 3-15
        rows = np.bincount(grid.cell_rc[:, 0])
        assert rows.tolist() == [7, 11, 13, 15, 15, 17, 17, 17, 17, 17, 17, 17, 15, 15, 13, 11, 7]


def test_layouts_give_the_thesis_phantoms():
    assert network_for_layout(get_layout("grid-4x4")).electrode_cells == thesis_phantom("C").electrode_cells
    assert network_for_layout(get_layout("square-16")).electrode_cells == thesis_phantom("B").electrode_cells
    refined = network_for_layout(get_layout("grid-4x4"), 3)
    assert refined.n_cells == 48 * 48 and all(len(c) == 9 for c in refined.electrode_cells)


# The thesis's projections: A and B drive electrodes 1-2, 2-3, 3-4, 4-5 (current in at the
# second, the first grounded); C drives 1-2, 2-3, 3-4, 5-6, 6-7, 7-8.
PROJECTIONS = {"A": [(2, 1), (3, 2), (4, 3), (5, 4)], "B": [(2, 1), (3, 2), (4, 3), (5, 4)],
               "C": [(2, 1), (3, 2), (4, 3), (6, 5), (7, 6), (8, 7)]}


@pytest.mark.parametrize("letter", ["A", "B", "C"])
@pytest.mark.parametrize(("contrast", "tolerance"), [(1.0, 1e-4), (1e-3, 1e-4), (1e3, 1e-2)])
def test_one_factorisation_agrees_with_the_thesis_procedure(letter, contrast, tolerance):
    """Our drive (current spread over the electrode's corners, one ground for all drives)
    and the thesis's (sink corners grounded, 1 A into each source corner) give the same
    electrode voltage differences to 1e-4 of their range with a centred anomaly. Where
    the anomaly is 1e3 and surrounds an electrode (phantom C's inner four), the metal is
    only ten times its surroundings and grounding all four corners is a real change of
    model: the two then differ by up to 1 %."""
    grid = thesis_phantom(letter)
    model = build_network_model(grid)
    centre = grid.centroids_mm.mean(axis=0)
    sigma = np.where(np.abs(grid.centroids_mm - centre).max(axis=1) < 25, contrast, 1.0)
    z = solve_electrodes(model, sigma).transfer
    for source, sink in PROJECTIONS[letter]:
        thesis = appendix_b_electrode_volts(grid, sigma, source, sink)
        mine = 4 * (z[:, source - 1] - z[:, sink - 1])   # the thesis injects 1 A at each of 4 corners
        difference = (mine - mine[sink - 1]) - (thesis - thesis[sink - 1])
        assert np.abs(difference).max() < tolerance * np.ptp(thesis)


def test_network_is_exactly_reciprocal():
    layout = get_layout("grid-4x4")
    model = build_network_model(network_for_layout(layout))
    protocol = default_protocol(layout)
    v = simulate(model, np.linspace(0.5, 2.0, model.n_elements), protocol)
    pairs = protocol.reciprocal_pairs()
    assert np.abs(v[pairs[:, 0]] - v[pairs[:, 1]]).max() < 1e-12 * np.abs(v).max()


def test_disc_network_converges_to_the_disc():
    layout = get_layout("circular-16")
    coarse, fine = network_for_layout(layout, 1), network_for_layout(layout, 4)
    area = np.pi * 50**2
    assert abs(fine.areas_mm2.sum() - area) < abs(coarse.areas_mm2.sum() - area)
    assert abs(fine.areas_mm2.sum() / area - 1) < 0.01


@pytest.mark.parametrize(("build", "message"), [
    (lambda: NetworkGrid(np.ones((2, 2), dtype=bool), 1.0, ((0,), (0,))), "two electrodes share one network element"),
    (lambda: NetworkGrid(np.ones((2, 2), dtype=bool), 1.0, ((0,), (9,))), "electrode 2: element 9 is not one of the 4"),
    (lambda: thesis_phantom("D"), "phantoms A, B and C"),
    (lambda: network_for_layout(get_layout("grid-3x5@400x800")), "do not fit one"),
    (lambda: network_for_layout(get_layout("grid-4x4"), 0), "refinement must be at least 1"),
])
def test_bad_networks_are_refused(build, message):
    with pytest.raises(LayoutInvalid, match=message):
        build()
