"""`mvgeo.common.imageio`: the name checks commands run before they write one output per input."""

import pytest


def test_check_distinct_stems_ignores_the_suffix_and_the_case(tmp_path):
    """Outputs are named `<stem>.png`: `a.png` and `a.jpg` would be one file, and so would `A.png` and
    `a.jpg` on a case-insensitive file system (macOS, Windows)."""
    from mvgeo.common.errors import InputError
    from mvgeo.common.imageio import check_distinct_stems

    check_distinct_stems(["a.png", "b.png", "ab.jpg"], path=tmp_path)
    for names in (["a.png", "a.jpg"], ["A.png", "b.png", "a.jpg"], ["x/v.png", "y/v.png"]):
        with pytest.raises(InputError, match="two images share the name") as err:
            check_distinct_stems(names, path=tmp_path)
        assert err.value.path == tmp_path and names[-1] in str(err.value)
