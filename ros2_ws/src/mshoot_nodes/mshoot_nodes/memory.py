"""
Bounded memory for received messages: what a node process sets before ``rclpy.init``.

A peer that publishes 10^6-element arrays must not grow a node's memory for good. The
validation (:mod:`mshoot_core.safety`) rejects such a message on its lengths before anything
is copied, but the message has been received and deserialised by then, and two layers below
rclpy kept the memory:

- Fast DDS keeps, by default in ROS (``PREALLOCATED_WITH_REALLOC``), every history slot of a
  reader and a writer at the largest sample size it ever held: a few huge messages on a
  depth-10 topic hold hundreds of MB. The profile written here makes readers and writers
  allocate each sample as it comes and free it once taken (``DYNAMIC``); it is used unless the
  process was given a profile of its own (``FASTRTPS_DEFAULT_PROFILES_FILE`` or
  ``FASTDDS_DEFAULT_PROFILES_FILE``).
- glibc raises its mmap threshold after a large block is freed, so the next large blocks come
  from the heap, which it does not give back; a fixed threshold of 128 kB keeps large blocks
  mapped and returned on free.

Measured with ``bench/hostile.py`` (see ``docs/security.md``).
"""
from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import pathlib
import tempfile

logger = logging.getLogger(__name__)

#: Fast DDS profile of every reader and writer of a node process.
FASTDDS_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_reader profile_name="mshoot_reader" is_default_profile="true">
    <historyMemoryPolicy>DYNAMIC</historyMemoryPolicy>
  </data_reader>
  <data_writer profile_name="mshoot_writer" is_default_profile="true">
    <historyMemoryPolicy>DYNAMIC</historyMemoryPolicy>
  </data_writer>
</profiles>
"""
#: ``mallopt`` parameter and the fixed threshold [bytes].
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 128 * 1024


def profile_path() -> pathlib.Path:
    """Write the profile once (under the temporary folder, named by its content); its path."""
    digest = hashlib.sha256(FASTDDS_PROFILE.encode()).hexdigest()[:12]
    path = pathlib.Path(tempfile.gettempdir()) / f'mshoot_fastdds_{digest}.xml'
    if not path.is_file():
        staged = path.with_name(f'.{path.name}.{os.getpid()}')
        staged.write_text(FASTDDS_PROFILE)
        staged.replace(path)
    return path


def bound_message_memory() -> None:
    """Set the Fast DDS profile and glibc's mmap threshold for this process (before init)."""
    if not any(os.environ.get(name) for name in ('FASTRTPS_DEFAULT_PROFILES_FILE',
                                                 'FASTDDS_DEFAULT_PROFILES_FILE')):
        try:
            os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(profile_path())
            # Only then does rmw_fastrtps take the history memory policy from the profile (the
            # QoS the nodes set still override the profile's).
            os.environ.setdefault('RMW_FASTRTPS_USE_QOS_FROM_XML', '1')
        except OSError as exc:
            logger.warning('Fast DDS profile not written (%s): received messages keep their '
                           'largest size in memory', exc)
    try:
        ctypes.CDLL('libc.so.6').mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    except (OSError, AttributeError):  # not glibc
        pass
