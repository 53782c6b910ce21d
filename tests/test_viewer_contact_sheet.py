import numpy as np

from viewer.contact_sheet import contact_sheet, pronounced_shapes


def test_sheet_tiles_show_each_shape(demo):
    rig, _ = demo
    names = pronounced_shapes(rig, 3)
    assert names[0] == "jawOpen"  # the jaw moves the face most on the demo rig
    sheet = contact_sheet(rig, names, columns=2, tile=(160, 160))
    assert sheet.shape == (320, 320, 3)
    tiles = [sheet[r:r + 160, c:c + 160].astype(int) for r in (0, 160) for c in (0, 160)]
    body = (slice(24, 160), slice(0, 160))  # below the label
    for shape_tile in tiles[1:]:
        changed = np.abs(shape_tile[body] - tiles[0][body]).max(axis=2) > 12
        assert changed.sum() > 20  # every shape visibly changes the picture
    assert tiles[0][body].std() > 10  # the neutral tile shows a lit face, not a flat fill
