"""The Fast DDS profile the node gives its own process when the user has set none, and the
advice it logs when a matched publisher's messages never arrive.

A full-size cloud (2 MB) sent best effort is lost on one host with Fast DDS's defaults: its
shared-memory segment (512 KiB) is overwritten before the reader copies the sample out, and the
UDP socket's receive buffer (208 KiB) overflows. The node's profile makes its readers listen on
UDP only, with a receive buffer of several samples, so a publisher with default settings reaches
it; and gives its writers a shared-memory segment that holds several labelled clouds, so a
best-effort consumer on the host gets them (see docs/ros2.md).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass
from pathlib import Path

#: The RMWs the profile is for; with another one (e.g. Cyclone DDS) the node applies nothing.
FASTDDS_RMWS = ("rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp")
#: The variables through which a user configures Fast DDS: with any set, the node applies nothing.
USER_SETTINGS = (
    "FASTDDS_DEFAULT_PROFILES_FILE",
    "FASTRTPS_DEFAULT_PROFILES_FILE",
    "RMW_FASTRTPS_USE_QOS_FROM_XML",
    "FASTDDS_BUILTIN_TRANSPORTS",
)
#: The profile files Fast DDS loads by itself from the working directory.
DEFAULT_PROFILE_FILES = ("DEFAULT_FASTDDS_PROFILES.xml", "DEFAULT_FASTRTPS_PROFILES.xml")
#: The UDP receive buffer the profile asks for (the kernel caps it at net.core.rmem_max, then
#: doubles it): 8 MiB, four full-size clouds.
RECEIVE_BUFFER = 8 * 2**20
#: Below this net.core.rmem_max (bytes), full-size best-effort clouds were lost: with the node
#: labelling on the CPU, 6 and 7 of 10 arrived at 1 MiB, 9 and 10 of 10 at 4 MiB (the one lost
#: sent as the publisher matched).
RMEM_MAX_NEEDED = 4 * 2**20
#: The shared-memory segment of the node's writers: several labelled clouds (3-5 MB each).
SHM_SEGMENT = 16 * 2**20
RMEM_MAX_PATH = Path("/proc/sys/net/core/rmem_max")

PROFILE_XML = f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- rangeret ros2: readers on UDP with a large receive buffer, writers with a large
     shared-memory segment; see docs/ros2.md. -->
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>rangeret_shm</transport_id>
        <type>SHM</type>
        <segment_size>{SHM_SEGMENT}</segment_size>
      </transport_descriptor>
      <transport_descriptor>
        <transport_id>rangeret_udp</transport_id>
        <type>UDPv4</type>
        <receiveBufferSize>{RECEIVE_BUFFER}</receiveBufferSize>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="rangeret_ros2" is_default_profile="true">
      <rtps>
        <useBuiltinTransports>false</useBuiltinTransports>
        <userTransports>
          <transport_id>rangeret_shm</transport_id>
          <transport_id>rangeret_udp</transport_id>
        </userTransports>
        <defaultUnicastLocatorList>
          <locator><udpv4><address>0.0.0.0</address></udpv4></locator>
        </defaultUnicastLocatorList>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


@dataclass(frozen=True)
class Transport:
    """What carries the node's messages: its own profile (`path`) or the user's settings."""

    #: The profile file the node wrote and applied; None when it applied nothing.
    path: Path | None
    #: How the log and the diagnostics name it.
    description: str
    #: net.core.rmem_max (bytes) where the node applied its profile and could read it.
    rmem_max: int | None = None

    @property
    def own(self) -> bool:
        """True when the node applied its own profile."""
        return self.path is not None

    def startup_warning(self) -> str | None:
        """A line for the log when the host caps the receive buffer below what a full-size
        best-effort cloud needs; None otherwise."""
        if not self.own or self.rmem_max is None or self.rmem_max >= RMEM_MAX_NEEDED:
            return None
        return (
            f"net.core.rmem_max is {self.rmem_max} bytes, which caps the node's UDP receive "
            "buffer: best-effort clouds of megabytes will be lost on the way. Raise it "
            f"(sudo sysctl -w net.core.rmem_max={RECEIVE_BUFFER}), or publish reliable and run "
            "with --input-qos reliable"
        )

    def remove(self) -> None:
        """Delete the profile file the node wrote (once ROS 2 is shut down)."""
        if self.path is not None:
            self.path.unlink(missing_ok=True)


def read_rmem_max(path: Path = RMEM_MAX_PATH) -> int | None:
    """The host's net.core.rmem_max in bytes; None where it cannot be read."""
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


def user_setting(environ: Mapping[str, str], cwd: Path) -> str | None:
    """What the user set that configures the middleware (a variable, another RMW, a profile
    file Fast DDS loads from `cwd`); None when nothing."""
    rmw = environ.get("RMW_IMPLEMENTATION", "")
    if rmw and rmw not in FASTDDS_RMWS:
        return f"RMW_IMPLEMENTATION={rmw}"
    for name in USER_SETTINGS:
        if environ.get(name):
            return f"{name}={environ[name]}"
    for name in DEFAULT_PROFILE_FILES:
        if (cwd / name).is_file():
            return str(cwd / name)
    return None


def apply_transport_profile(
    environ: MutableMapping[str, str] = os.environ, cwd: Path | None = None
) -> Transport:
    """Write the node's Fast DDS profile and point `environ` (this process, before rclpy starts)
    at it, unless the user has configured the middleware; what carries the messages."""
    setting = user_setting(environ, Path.cwd() if cwd is None else cwd)
    if setting is not None:
        return Transport(None, f"the user's middleware settings ({setting})")
    fd, name = tempfile.mkstemp(prefix="rangeret-fastdds-", suffix=".xml")
    with os.fdopen(fd, "w") as out:
        out.write(PROFILE_XML)
    environ["FASTDDS_DEFAULT_PROFILES_FILE"] = name
    description = (
        f"the node's Fast DDS profile (UDP receive buffer {RECEIVE_BUFFER // 2**20} MiB, "
        f"shared-memory segment {SHM_SEGMENT // 2**20} MiB)"
    )
    return Transport(Path(name), description, read_rmem_max())


def silence_advice(
    topic: str, publishers: int, reliable: bool | None, transport: Transport, seconds: float
) -> str:
    """What to change when `publishers` publishers of `topic`, matched for `seconds`, sent
    nothing that arrived (`reliable`: whether they publish reliable; None when unknown)."""
    head = (
        f"{topic}: {publishers} matched publisher{'s' if publishers != 1 else ''} for "
        f"{seconds:g} s, but no message has arrived"
    )
    reliable_fix = "have the publisher publish reliable and run with --input-qos reliable"
    if reliable:
        return (
            f"{head}. They publish reliable: run with --input-qos reliable, which lets them "
            "resend what is lost on the way (see docs/ros2.md)"
        )
    kind = "" if reliable is None else ". They publish best effort"
    if not transport.own:
        fix = (
            f"with {transport.description}, a cloud of megabytes sent best effort arrives only "
            f"when this subscriber listens on UDP alone with a receive buffer of "
            f"{RECEIVE_BUFFER // 2**20} MiB, or the publisher has a shared-memory segment of "
            f"several clouds; or {reliable_fix}"
        )
    elif transport.rmem_max is not None and transport.rmem_max < RMEM_MAX_NEEDED:
        fix = (
            f"net.core.rmem_max ({transport.rmem_max} bytes) caps the node's UDP receive buffer "
            "below one cloud of megabytes sent best effort: raise it (sudo sysctl -w "
            f"net.core.rmem_max={RECEIVE_BUFFER}), or {reliable_fix}"
        )
    else:
        fix = (
            "the node's UDP receive buffer holds several clouds, so either nothing was "
            "published, or it was lost before reaching this host (a publisher's own Fast DDS "
            f"profile, the network); {reliable_fix}"
        )
    return f"{head}{kind}: {fix} (see docs/ros2.md)"
