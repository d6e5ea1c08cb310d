"""frames_processed.txt: a live run's tracked frames and the yield point each was tracked at."""
import pytest

from vigs_core.io import read_frame_schedule, write_frame_schedule


def test_schedule_round_trip_and_stamps_only_files(tmp_path):
    path = tmp_path / "frames_processed.txt"
    write_frame_schedule(path, [(100, None), (150, 3), (200, 4), (250, None)])
    assert read_frame_schedule(path) == {100: None, 150: 3, 200: 4, 250: None}
    path.write_text("# stamps only\n100\n\n250, \n")   # the older one-column form: every frame between frames
    assert read_frame_schedule(path) == {100: None, 250: None}


@pytest.mark.parametrize("text, says", [("100 2 7\n", ":1: expected a stamp"), ("100\nabc\n", ":2: expected a stamp"),
                                        ("# nothing\n", "no frame stamps")])
def test_malformed_schedules_are_named(tmp_path, text, says):
    path = tmp_path / "s.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=says):
        read_frame_schedule(path)
