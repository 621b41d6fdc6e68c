"""A recording on disk: a rosbag2 MCAP directory or a bare ``.mcap`` file.

:func:`read_rosbag2_metadata` checks a rosbag2 directory's ``metadata.yaml``
(storage ``mcap``, no rosbag2-level compression) and lists its MCAP files
(``relative_file_paths``, in reading order).  :class:`McapRecording` opens
either form and reads its files in order: :meth:`McapRecording.topics`
(channels over all files) and :meth:`McapRecording.iter_batches` (the
messages of selected topics, one :class:`MessageBatch` per chunk, with
progress).

One MCAP file: :mod:`imu_array_ros.io.rosbag.mcap_reader`; messages located
in a chunk: :mod:`imu_array_ros.io.rosbag.mcap_locate`; the recording API
(topics and message semantics): :mod:`imu_array_ros.io.rosbag.recording`.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable, Iterator, Mapping

from imu_array_ros.errors import RecordingError
from imu_array_ros.io.rosbag.mcap_locate import MessageBatch
from imu_array_ros.io.rosbag.mcap_reader import McapFile
from imu_array_ros.io.rosbag.mcap_summary import ChannelInfo, recover_command
from imu_array_ros.util.files import load_yaml_file

__all__ = ["McapRecording", "read_rosbag2_metadata"]


def read_rosbag2_metadata(directory: str | os.PathLike) -> tuple[list[Path], dict]:
    """The MCAP files (in reading order) and ``rosbag2_bagfile_information`` of a rosbag2 directory."""
    directory = Path(directory)
    meta_path = directory / "metadata.yaml"
    if not meta_path.is_file():
        mcaps = sorted(p.name for p in directory.glob("*.mcap"))
        hint = (
            f" (it has {', '.join(mcaps[:3])}: pass the .mcap file, or rebuild the directory with "
            f"{recover_command(directory)})"
            if mcaps
            else ""
        )
        raise RecordingError(f"{directory}: not a rosbag2 directory: no metadata.yaml{hint}")
    doc = load_yaml_file(meta_path, RecordingError, "rosbag2 metadata")
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise RecordingError(f"{meta_path}: malformed metadata: no rosbag2_bagfile_information mapping")
    storage = info.get("storage_identifier")
    if storage != "mcap":
        raise RecordingError(
            f"{meta_path}: storage_identifier is {storage!r}; only 'mcap' is supported "
            "(convert with `ros2 bag convert` to mcap)"
        )
    mode = str(info.get("compression_mode") or "").strip().lower()
    if mode not in ("", "none"):
        raise RecordingError(
            f"{meta_path}: rosbag2 compression_mode {mode!r} is not supported "
            "(use MCAP chunk compression: `ros2 bag convert` / `ros2 bag record --storage-preset-profile`)"
        )
    rel = info.get("relative_file_paths")
    if not isinstance(rel, list) or not rel or not all(isinstance(x, str) and x for x in rel):
        raise RecordingError(f"{meta_path}: malformed metadata: relative_file_paths must be a non-empty list of file names")
    files = []
    for name in rel:
        p = directory / name
        if not p.is_file():
            raise RecordingError(f"{meta_path}: relative_file_paths lists {name!r}, which does not exist")
        files.append(p)
    return files, info


class McapRecording:
    """A recording: rosbag2 MCAP directory or bare ``.mcap`` file.

    ``files`` are the MCAP files in reading order; ``metadata`` the
    ``rosbag2_bagfile_information`` mapping (None for a bare file).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        p = Path(path)
        if p.name == "metadata.yaml" and p.is_file():
            p = p.parent
        self.path = p
        if not p.exists():
            raise RecordingError(f"{p}: recording not found")
        self.metadata: dict | None
        if p.is_dir():
            self.files, self.metadata = read_rosbag2_metadata(p)
        elif p.is_file():
            self.files, self.metadata = [p], None
        else:
            raise RecordingError(f"{p}: not a file or directory")
        self._channels: dict[Path, list[ChannelInfo]] = {}  # files whose channels are all known
        self._summarized: bool | None = None

    def open_files(self) -> Iterator[McapFile]:
        for f in self.files:
            with McapFile(f, source=self.path) as mf:
                if mf.has_summary:
                    self._channels[f] = list(mf.channels.values())
                yield mf

    @property
    def topics_known(self) -> bool:
        """True when every file's summary lists its channels: :meth:`topics` reads no messages."""
        if self._summarized is None:
            summarized = True
            for f in self.files:
                with McapFile(f, source=self.path) as mf:
                    if mf.has_summary:
                        self._channels[f] = list(mf.channels.values())
                    else:
                        summarized = False
            self._summarized = summarized
        return self._summarized

    def topics(self) -> dict[str, list[ChannelInfo]]:
        """topic -> channels over all files.

        From the summaries; a file without one is read through once (channel
        records may hide in chunks) unless an earlier complete
        :meth:`iter_batches` pass already met its channels.  Callers that read
        the messages anyway and check topics afterwards (``topics_known``
        False) decompress each chunk only once.
        """
        out: dict[str, list[ChannelInfo]] = {}
        for f in self.files:
            if f not in self._channels:
                with McapFile(f, source=self.path) as mf:
                    if not mf.has_summary:
                        for _ in mf.iter_batches(lambda ch: -1):
                            pass
                    self._channels[f] = list(mf.channels.values())
            for ch in self._channels[f]:
                out.setdefault(ch.topic, []).append(ch)
        return out

    def iter_batches(
        self,
        select: Mapping[str, str],
        *,
        encoding: str = "cdr",
        progress: Callable[[float], None] | None = None,
    ) -> Iterator[MessageBatch]:
        """Batches of the messages on topics ``select`` (topic -> schema name).

        A channel is selected when its topic is a key of ``select``, its schema
        name equals the value and its message encoding is ``encoding``;
        ``MessageBatch.topic`` indexes ``list(select)``.  ``progress(f)`` gets
        the fraction of file bytes done, now and then.
        """
        index = {t: i for i, t in enumerate(select)}

        def choose(ch: ChannelInfo) -> int:
            i = index.get(ch.topic, -1)
            if i >= 0 and ch.schema_name == select[ch.topic] and ch.message_encoding == encoding:
                return i
            return -1

        total = sum(max(f.stat().st_size, 1) for f in self.files)
        done_files = 0
        last = -1.0
        for mf in self.open_files():
            fsize = max(mf.size, 1)
            done = 0
            with contextlib.closing(mf.iter_batches(choose)) as batches:
                for used, batch in batches:
                    done += used
                    if progress is not None:
                        frac = (done_files + fsize * min(done / fsize, 1.0)) / total
                        if frac - last >= 0.01:
                            progress(frac)
                            last = frac
                    if len(batch):
                        yield batch
            self._channels[mf.path] = list(mf.channels.values())  # complete after a whole pass
            done_files += fsize
        if progress is not None and last < 1.0:
            progress(1.0)
