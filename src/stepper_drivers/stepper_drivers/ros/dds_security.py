"""Whether the ROS middleware of this process can run SROS2 (DDS-Security), asked before
rclpy.init so that a node that cannot be secured says so in one line.

With ROS_SECURITY_ENABLE=true rcl hands the enclave's certificates and permissions to the
middleware. rmw_fastrtps compiles its security code only when its Fast DDS has the security
plugins (`#if HAVE_SECURITY` in rmw_fastrtps_shared_cpp/src/participant.cpp, Jazzy; Fast DDS
defines HAVE_SECURITY in its config.h from its SECURITY=ON build option). Without them, creating
the node fails with "This Fast DDS version doesn't have the security libraries", after rcl's own
log lines, and in Permissive mode without a keystore rcl runs the node unsecured without a word.

How the plugins are found: the Fast DDS library the rmw loaded is read for the C++ namespace of
the security plugins, `eprosima::fastrtps::rtps::security` (`eprosima::fastdds::rtps::security`
from Fast DDS 3), mangled `...4rtps8security...`. Its classes (SecurityManager, PKIDH,
Permissions, AESGCMGMAC) are polymorphic, so their type-info names are in the library's read-only
data even when the library is stripped or hides its symbols; a build without SECURITY=ON has no
such name at all. This asks the library the rmw really uses (found in /proc/self/maps after
rclpy loaded the rmw), whatever installed it, and creates no participant. When it cannot tell (an
rmw other than rmw_fastrtps, no Fast DDS library mapped, a file it cannot read) it says nothing
and the rmw decides. No rclpy import at module level.
"""

from __future__ import annotations

import mmap
import os
import re
from typing import Iterable, Mapping

# The mangled namespace of the Fast DDS security plugins (2.x: fastrtps, 3.x: fastdds).
SECURITY_NAMESPACE = b'4rtps8security'
_FAST_DDS_LIBRARY = re.compile(r'libfast(rtps|dds)\.so')


def security_requested(environ: Mapping[str, str] = os.environ) -> bool:
    """rcl's rule (rcl/security.c, rcl_security_enabled): security is on when
    ROS_SECURITY_ENABLE is exactly 'true'."""
    return environ.get('ROS_SECURITY_ENABLE', '') == 'true'


def has_security_plugins(library: str) -> bool | None:
    """Whether a Fast DDS library file has the security plugins; None: it cannot be read."""
    try:
        with open(library, 'rb') as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
            return m.find(SECURITY_NAMESPACE) >= 0
    except (OSError, ValueError):
        return None


def mapped_fast_dds_libraries(maps: str = '/proc/self/maps') -> list[str]:
    """The Fast DDS libraries mapped into this process, each once."""
    found: list[str] = []
    try:
        with open(maps, encoding='utf-8', errors='replace') as f:
            for line in f:       # address perms offset dev inode [path] (proc(5))
                fields = line.split(maxsplit=5)
                path = fields[5].strip() if len(fields) == 6 else ''
                if _FAST_DDS_LIBRARY.match(os.path.basename(path)) and path not in found:
                    found.append(path)
    except OSError:
        pass
    return found


def problem(rmw: str, libraries: Iterable[str]) -> str:
    """The one line why `rmw` with these Fast DDS libraries cannot run SROS2, or ''."""
    if not rmw.startswith('rmw_fastrtps'):
        return ''
    libraries = list(libraries)
    answers = [has_security_plugins(lib) for lib in libraries]
    if not libraries or any(a is not False for a in answers):
        return ''
    return (f'ROS_SECURITY_ENABLE=true, but the Fast DDS of {rmw} ({", ".join(libraries)}) '
            'has no DDS-Security plugins (built without SECURITY=ON), so this node cannot '
            'join a secured ROS graph: run it on a ROS install whose Fast DDS has them (the '
            'ROS 2 Jazzy apt packages; docs/security.md), or unset ROS_SECURITY_ENABLE')


def startup_problem(environ: Mapping[str, str] = os.environ) -> str:
    """'' unless security is requested and the middleware cannot provide it (the line to
    print). Loads the rmw library (rclpy), creates no context or participant."""
    if not security_requested(environ):
        return ''
    try:
        from rclpy.utilities import get_rmw_implementation_identifier
        rmw = get_rmw_implementation_identifier()
    except Exception:  # noqa: BLE001 - no rmw to ask: rclpy.init reports it
        return ''
    return problem(rmw, mapped_fast_dds_libraries())
