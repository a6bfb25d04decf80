"""PNG writing: checked by an independent decoder written here, not by re-reading our own encoder."""

import struct
import zlib

import numpy as np
import pytest

from appliance.core.render import colourise, encode_png, labels_to_rgba, write_png
from appliance.errors import ModelInputInvalid

SIGNATURE = b"\x89PNG\r\n\x1a\n"


def parse_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """Split a PNG into (type, payload) chunks, checking the signature and every CRC."""
    assert data[:8] == SIGNATURE, "missing PNG signature"
    chunks, pos = [], 8
    while pos < len(data):
        assert pos + 12 <= len(data), "truncated chunk"
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        tag, payload = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        if crc != zlib.crc32(tag + payload) & 0xFFFFFFFF:
            raise AssertionError(f"bad CRC in {tag!r} chunk")
        chunks.append((tag, payload))
        pos += 12 + length
    assert chunks[-1] == (b"IEND", b""), "PNG does not end with an empty IEND"
    return chunks


def decode_png(data: bytes) -> np.ndarray:
    """Decode an 8-bit RGBA, non-interlaced, filter-type-0 PNG to an (H, W, 4) uint8 array."""
    chunks = parse_chunks(data)
    assert chunks[0][0] == b"IHDR"
    width, height, depth, colour, compression, filtering, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert (depth, colour, compression, filtering, interlace) == (8, 6, 0, 0, 0)
    raw = zlib.decompress(b"".join(p for t, p in chunks if t == b"IDAT"))
    rows = np.frombuffer(raw, np.uint8).reshape(height, 1 + 4 * width)
    if np.any(rows[:, 0] != 0):
        raise AssertionError(f"row filter types {sorted(set(rows[:, 0].tolist()))}, only 0 (None) supported")
    return rows[:, 1:].reshape(height, width, 4)  # filter type 0: bytes are the pixels as they are


def ihdr_size(data: bytes) -> tuple[int, int]:
    """(width, height) from the IHDR chunk."""
    tag, payload = parse_chunks(data)[0]
    assert tag == b"IHDR"
    return struct.unpack(">II", payload[:8])


# --- encode_png -------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(1, 1), (3, 7), (7, 3), (16, 16), (2, 50)])
def test_encode_then_decode_returns_the_input_exactly(rng, shape):
    rgba = rng.integers(0, 256, size=shape + (4,), dtype=np.uint8)
    decoded = decode_png(encode_png(rgba))
    assert decoded.shape == rgba.shape
    np.testing.assert_array_equal(decoded, rgba)


def test_chunk_layout_is_ihdr_one_idat_iend(rng):
    data = encode_png(rng.integers(0, 256, size=(5, 4, 4), dtype=np.uint8))
    assert [tag for tag, _ in parse_chunks(data)] == [b"IHDR", b"IDAT", b"IEND"]
    assert ihdr_size(data) == (4, 5)


def test_decoder_catches_a_corrupted_crc():
    data = bytearray(encode_png(np.full((2, 2, 4), 7, np.uint8)))
    data[8 + 8 + 3] ^= 0xFF  # a byte of the IHDR width, covered by the IHDR CRC
    with pytest.raises(AssertionError, match="bad CRC in b'IHDR'"):
        parse_chunks(bytes(data))


def test_non_contiguous_input_is_encoded_as_seen(rng):
    rgba = rng.integers(0, 256, size=(6, 8, 4), dtype=np.uint8)[::2, ::-1]
    np.testing.assert_array_equal(decode_png(encode_png(rgba)), rgba)


@pytest.mark.parametrize("bad", [np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2, 4), float),
                                 np.zeros((0, 3, 4), np.uint8), np.zeros((4, 4), np.uint8)])
def test_encode_rejects_anything_but_nonempty_rgba_uint8(bad):
    with pytest.raises(ModelInputInvalid, match=r"\(H, W, 4\) uint8"):
        encode_png(bad)


# --- colourise --------------------------------------------------------------------------------------

@pytest.mark.parametrize("palette", ["diverging", "sequential"])
def test_nan_is_fully_transparent_and_finite_is_opaque(palette):
    values = np.array([[np.nan, 0.0, 0.5], [1.0, np.nan, -1.0]])
    rgba = colourise(values, -1.0, 1.0, palette)
    np.testing.assert_array_equal(rgba[..., 3], [[0, 255, 255], [255, 0, 255]])


def test_diverging_white_at_zero_blue_at_vmin_red_at_vmax():
    rgba = colourise(np.array([[-3.0, 0.0, 3.0]]), -3.0, 3.0)
    assert rgba[0, 0].tolist() == [0, 0, 255, 255]
    assert rgba[0, 1].tolist() == [255, 255, 255, 255]
    assert rgba[0, 2].tolist() == [255, 0, 0, 255]


def test_diverging_is_linear_halfway():
    rgba = colourise(np.array([[-1.0, 1.0]]), -2.0, 2.0)
    assert rgba[0, 0, :3].tolist() == [128, 128, 255]
    assert rgba[0, 1, :3].tolist() == [255, 128, 128]


def test_diverging_is_monotonic_in_red_and_blue():
    rgba = colourise(np.linspace(-5.0, 5.0, 201)[None, :], -5.0, 5.0).astype(int)
    red, green, blue = rgba[0, :, 0], rgba[0, :, 1], rgba[0, :, 2]
    assert np.all(np.diff(red) >= 0) and red[0] == 0 and red[-1] == 255
    assert np.all(np.diff(blue) <= 0) and blue[0] == 255 and blue[-1] == 0
    assert green.argmax() == 100 and green[100] == 255  # lightest at zero
    assert np.all(np.diff(red[:101]) > 0) and np.all(np.diff(blue[100:]) < 0)  # no flat stretches


def test_diverging_is_symmetric_about_zero_even_for_an_asymmetric_range():
    rgba = colourise(np.array([[-1.0, 1.0, 0.0]]), -1.0, 3.0)
    neg, pos = rgba[0, 0, :3].tolist(), rgba[0, 1, :3].tolist()
    assert neg == pos[::-1]  # (r, g, b) at -1 mirrors (b, g, r) at +1
    assert neg == [170, 170, 255]  # one third of the way to blue
    assert rgba[0, 2, :3].tolist() == [255, 255, 255]


def test_values_outside_the_range_are_clipped():
    rgba = colourise(np.array([[-100.0, -np.inf, 100.0, np.inf]]), -1.0, 1.0)
    assert rgba[0, :, :3].tolist() == [[0, 0, 255], [0, 0, 255], [255, 0, 0], [255, 0, 0]]


def test_sequential_white_at_vmin_to_dark_blue_at_vmax():
    rgba = colourise(np.linspace(0.0, 100.0, 101)[None, :], 0.0, 100.0, "sequential").astype(int)
    assert rgba[0, 0].tolist() == [255, 255, 255, 255]
    assert rgba[0, -1].tolist() == [8, 48, 107, 255]
    assert np.all(np.diff(rgba[0, :, :3], axis=0) <= 0)  # darker in every channel as the value grows
    assert rgba[0, -1, 2] > rgba[0, -1, 0] + 50  # blue dominates


@pytest.mark.parametrize("vmin, vmax", [(1.0, 1.0), (2.0, 1.0), (np.nan, 1.0), (0.0, np.inf), (-np.inf, 0.0)])
def test_colourise_rejects_a_bad_range(vmin, vmax):
    with pytest.raises(ModelInputInvalid, match="finite vmin < vmax"):
        colourise(np.zeros((2, 2)), vmin, vmax)


def test_colourise_rejects_unknown_palette_and_wrong_shape():
    with pytest.raises(ModelInputInvalid, match="unknown palette 'viridis'"):
        colourise(np.zeros((2, 2)), -1.0, 1.0, "viridis")
    with pytest.raises(ModelInputInvalid, match=r"2-D \(H, W\).*\(4,\)"):
        colourise(np.zeros(4), -1.0, 1.0)


def test_range_errors_are_value_errors():
    with pytest.raises(ValueError):
        colourise(np.zeros((1, 1)), 1.0, 0.0)


# --- labels_to_rgba ---------------------------------------------------------------------------------

def test_labels_get_three_clearly_different_opaque_colours():
    rgba = labels_to_rgba(np.array([[0, 1, 2], [2, 1, 0]])).astype(int)
    assert rgba.dtype == int and rgba.shape == (2, 3, 4)
    assert np.all(rgba[..., 3] == 255)
    np.testing.assert_array_equal(rgba[0], rgba[1, ::-1])  # same label, same colour
    colours = rgba[0, :, :3]
    for i in range(3):
        for j in range(i + 1, 3):
            assert np.abs(colours[i] - colours[j]).sum() > 150, (i, j)


@pytest.mark.parametrize("bad, shown", [(3, "3"), (-1, "-1"), (1.5, "1.5"), (np.nan, "nan")])
def test_labels_reject_an_unknown_label_naming_it(bad, shown):
    labels = np.zeros((2, 2)) if isinstance(bad, float) else np.zeros((2, 2), int)
    labels[1, 0] = bad
    with pytest.raises(ModelInputInvalid, match=rf"label {shown} at row 1, column 0 is not 0 \(water\)"):
        labels_to_rgba(labels)


def test_labels_reject_a_non_2d_array():
    with pytest.raises(ModelInputInvalid, match="2-D"):
        labels_to_rgba(np.zeros(5, int))


# --- write_png --------------------------------------------------------------------------------------

def test_write_png_scale_repeats_every_pixel(tmp_path, rng):
    values = rng.normal(size=(4, 5))
    path = tmp_path / "map.png"
    write_png(path, values, vmin=-2.0, vmax=2.0, scale=3)
    data = path.read_bytes()
    assert ihdr_size(data) == (15, 12)
    decoded = decode_png(data)
    small = colourise(values, -2.0, 2.0)
    for i in range(4):
        for j in range(5):
            block = decoded[3 * i:3 * i + 3, 3 * j:3 * j + 3].reshape(9, 4)
            assert np.all(block == small[i, j]), (i, j)


@pytest.mark.parametrize("shape, scale", [((16, 16), 16), ((3, 7), 1), ((1, 1), 2)])
def test_write_png_header_size_matches(tmp_path, shape, scale):
    path = tmp_path / "m.png"
    write_png(str(path), np.zeros(shape), scale=scale)
    assert ihdr_size(path.read_bytes()) == (shape[1] * scale, shape[0] * scale)


def test_write_png_default_diverging_range_is_plus_minus_max_abs(tmp_path):
    path = tmp_path / "d.png"
    write_png(path, np.array([[-2.0, 1.0, np.nan]]))
    decoded = decode_png(path.read_bytes())
    assert decoded[0].tolist() == [[0, 0, 255, 255], [255, 128, 128, 255], [0, 0, 0, 0]]


def test_write_png_default_sequential_range_is_the_data_range(tmp_path):
    path = tmp_path / "s.png"
    write_png(path, np.array([[20.0, 60.0], [np.nan, 40.0]]), palette="sequential")
    decoded = decode_png(path.read_bytes())
    assert decoded[0, 0].tolist() == [255, 255, 255, 255]
    assert decoded[0, 1].tolist() == [8, 48, 107, 255]
    assert decoded[1, 0, 3] == 0


@pytest.mark.parametrize("palette", ["diverging", "sequential"])
@pytest.mark.parametrize("fill", [np.nan, 0.0, 42.0])
def test_write_png_handles_all_nan_all_zero_and_constant_images(tmp_path, palette, fill):
    path = tmp_path / "flat.png"
    write_png(path, np.full((3, 4), fill), palette=palette, scale=2)
    decoded = decode_png(path.read_bytes())
    assert decoded.shape == (6, 8, 4)
    if np.isnan(fill):
        assert np.all(decoded == 0)
    elif fill == 0.0 or palette == "sequential":
        assert np.all(decoded == 255)  # white: zero (diverging) or vmin (sequential)
    else:
        assert np.all(decoded[..., :3] == [255, 0, 0])  # diverging: the single value is the maximum


@pytest.mark.parametrize("values", [np.zeros(4), np.zeros((2, 2, 2)), 3.0])
def test_write_png_rejects_non_2d_input(tmp_path, values):
    with pytest.raises(ModelInputInvalid, match=r"2-D \(H, W\)"):
        write_png(tmp_path / "x.png", values)
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("scale", [0, -2, 1.5, "2", True])
def test_write_png_rejects_a_bad_scale(tmp_path, scale):
    with pytest.raises(ModelInputInvalid, match="scale must be an integer >= 1"):
        write_png(tmp_path / "x.png", np.zeros((2, 2)), scale=scale)
    assert not (tmp_path / "x.png").exists()


def test_write_png_passes_a_bad_explicit_range_on_as_an_error(tmp_path):
    with pytest.raises(ModelInputInvalid, match="vmin=5.0, vmax=1.0"):
        write_png(tmp_path / "x.png", np.zeros((2, 2)), vmin=5.0, vmax=1.0)
