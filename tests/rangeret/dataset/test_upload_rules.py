"""Each layout gives the rules of its own uploaded archives: a built-in profile's layout takes a
scan named as its layout names one and refuses a scan named as the other layout does."""

from __future__ import annotations

import pytest

from rangeret.dataset.profiles import BUILTIN_PROFILES, load_profile
from rangeret.dataset.upload_rules import ArchiveError

FOLDER_SCAN = "sequences/08/velodyne/000000.bin"
TABLE_SCAN = "samples/LIDAR_TOP/n008-2018-08-01__LIDAR_TOP__1533151603547590.pcd.bin"


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_a_layout_takes_its_own_scans_and_refuses_the_other_layouts(name):
    profile = load_profile(name)
    own, other = (
        (TABLE_SCAN, FOLDER_SCAN) if profile.layout.folders is None else (FOLDER_SCAN, TABLE_SCAN)
    )
    rules = profile.layout.upload_rules(profile.points)
    rules.check_name(own, is_dir=False)
    assert rules.point_bytes(own) == profile.points.point_bytes
    with pytest.raises(ArchiveError, match="is not a"):
        profile.layout.upload_rules(profile.points).check_name(other, is_dir=False)
