"""Names that moved out of ladar_addon/properties.py and ladar_addon/simulate.py (layered layout) keep their old
path for now: the very same object, with a DeprecationWarning naming the new module (ladar_addon/moved.py)."""
import pytest

CASES = [("properties", "set_settings", "blend_config"), ("properties", "all_core_paths", "fields"),
         ("simulate", "parse_frames", "frames"), ("simulate", "current_job", "job"),
         ("simulate", "build_config", "run_inputs")]


@pytest.mark.parametrize("old, name, new", CASES)
def test_old_path_is_the_moved_object_and_says_where_to_go(lad, old, name, new):
    with pytest.warns(DeprecationWarning, match=rf"ladar_addon\.{old}\.{name} has moved to ladar_addon\.{new}\.{name}"):
        obj = getattr(getattr(lad, old), name)
    assert obj is getattr(getattr(lad, new), name)


def test_unknown_names_are_not_invented(lad):
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        lad.simulate.no_such_name  # noqa: B018
