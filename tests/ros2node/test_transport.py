"""The node's Fast DDS profile: applied to its own process only when the user configured none,
what it sets, the rmem_max warning and the advice for a matched publisher whose messages never
arrive. No ROS 2 runs here."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from ros2node.transport import (
    PROFILE_XML,
    RECEIVE_BUFFER,
    RMEM_MAX_NEEDED,
    SHM_SEGMENT,
    Transport,
    apply_transport_profile,
    read_rmem_max,
    silence_advice,
    user_setting,
)

NS = {"f": "http://www.eprosima.com"}


def test_the_profile_gives_readers_udp_alone_with_a_large_buffer_and_writers_a_large_segment():
    root = ET.fromstring(PROFILE_XML)
    descriptors = {
        d.findtext("f:type", namespaces=NS): d
        for d in root.iterfind(".//f:transport_descriptor", NS)
    }
    assert (
        int(descriptors["UDPv4"].findtext("f:receiveBufferSize", namespaces=NS)) == RECEIVE_BUFFER
    )
    assert int(descriptors["SHM"].findtext("f:segment_size", namespaces=NS)) == SHM_SEGMENT
    participant = root.find(".//f:participant", NS)
    assert participant.get("is_default_profile") == "true"
    assert participant.findtext(".//f:useBuiltinTransports", namespaces=NS) == "false"
    locators = participant.findall(".//f:defaultUnicastLocatorList/f:locator/*", NS)
    assert [loc.tag.split("}")[1] for loc in locators] == ["udpv4"]
    assert locators[0].findtext("f:address", namespaces=NS) == "0.0.0.0"


def test_the_node_writes_and_points_its_own_process_at_the_profile(tmp_path):
    environ = {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    transport = apply_transport_profile(environ, cwd=tmp_path)
    try:
        assert transport.own and environ["FASTDDS_DEFAULT_PROFILES_FILE"] == str(transport.path)
        assert transport.path.read_text() == PROFILE_XML
        assert "UDP receive buffer 8 MiB, shared-memory segment 16 MiB" in transport.description
    finally:
        transport.remove()
    assert not transport.path.exists()


@pytest.mark.parametrize(
    ("environ", "named"),
    [
        ({"FASTDDS_DEFAULT_PROFILES_FILE": "/etc/dds.xml"}, "FASTDDS_DEFAULT_PROFILES_FILE"),
        ({"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/dds.xml"}, "FASTRTPS_DEFAULT_PROFILES_FILE"),
        ({"RMW_FASTRTPS_USE_QOS_FROM_XML": "1"}, "RMW_FASTRTPS_USE_QOS_FROM_XML"),
        ({"FASTDDS_BUILTIN_TRANSPORTS": "LARGE_DATA"}, "FASTDDS_BUILTIN_TRANSPORTS"),
        ({"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}, "RMW_IMPLEMENTATION=rmw_cyclonedds_cpp"),
    ],
)
def test_a_users_middleware_setting_is_left_alone(tmp_path, environ, named):
    before = dict(environ)
    transport = apply_transport_profile(environ, cwd=tmp_path)
    assert not transport.own and environ == before
    assert named in transport.description
    assert transport.startup_warning() is None


def test_a_profile_file_fast_dds_loads_from_the_working_directory_is_left_alone(tmp_path):
    (tmp_path / "DEFAULT_FASTDDS_PROFILES.xml").write_text("<dds/>")
    assert user_setting({}, tmp_path) == str(tmp_path / "DEFAULT_FASTDDS_PROFILES.xml")
    assert user_setting({"RMW_IMPLEMENTATION": "rmw_fastrtps_dynamic_cpp"}, tmp_path.parent) is None


def test_rmem_max_is_read_and_a_small_one_is_a_startup_warning(tmp_path):
    (tmp_path / "rmem_max").write_text("212992\n")
    assert read_rmem_max(tmp_path / "rmem_max") == 212992
    assert read_rmem_max(tmp_path / "missing") is None
    small = Transport(tmp_path / "p.xml", "own", 212992)
    assert "net.core.rmem_max=8388608" in small.startup_warning()
    assert Transport(tmp_path / "p.xml", "own", RMEM_MAX_NEEDED).startup_warning() is None
    assert Transport(tmp_path / "p.xml", "own", None).startup_warning() is None


def test_the_silence_advice_names_what_to_change():
    own = Transport(None, "x")
    reliable = silence_advice("/points", 1, True, own, 10.0)
    assert reliable.startswith("/points: 1 matched publisher for 10 s, but no message has arrived")
    assert "They publish reliable: run with --input-qos reliable" in reliable
    small = Transport(Path("p.xml"), "own", 212992)
    assert "sudo sysctl -w net.core.rmem_max=8388608" in silence_advice("/p", 2, False, small, 10.0)
    assert "2 matched publishers" in silence_advice("/p", 2, False, small, 10.0)
    user = Transport(None, "the user's middleware settings (FASTDDS_DEFAULT_PROFILES_FILE=/x)")
    advice = silence_advice("/p", 1, None, user, 10.0)
    assert "FASTDDS_DEFAULT_PROFILES_FILE=/x" in advice and "UDP alone" in advice
    assert "--input-qos reliable" in advice and "They publish" not in advice
