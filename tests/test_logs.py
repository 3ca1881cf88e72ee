"""OnFly logs: bit-for-bit round trip, streaming reads, truncation and corruption."""

from __future__ import annotations

import json
import struct
from itertools import islice
from pathlib import Path

import numpy as np
import pytest

from onfly.logs import LogCorruptError, LogError, LogExistsError, LogFormatError, LogReader, LogWriter, LogWriterConfig
from onfly.logs.format import FILE_MAGIC, PREFIX_SIZE
from onfly.observation import Observation
from onfly.readers.tum import TumReader
from planning.camera import PinholeCamera
from planning.frames import T_BODY_CAM, body_transform, cam_transform_from_body
from vlm.types import FrameAnnotation, VisibleObject
from realdata_paths import REALDATA

KITCHEN = REALDATA / "7scenes-kitchen-tum"


def random_observations(n: int, seed: int = 0, annotated: bool = False) -> list[Observation]:
    rng = np.random.default_rng(seed)
    cam = PinholeCamera(32, 24, 20.5, 21.25, 15.5, 11.5)
    out = []
    for k in range(n):
        depth = rng.uniform(0.1, 30.0, size=cam.shape).astype(np.float32)
        depth[0, :3] = [np.nan, np.inf, 0.0]
        depth[1, 0] = np.float32(np.frombuffer(np.uint32(0x7FC00123).tobytes(), np.float32)[0])  # NaN payload
        ann = None
        if annotated:
            ann = FrameAnnotation(
                instance_ids=rng.integers(0, 4, size=cam.shape, dtype=np.int32),
                depth_m=depth.copy(),
                objects={3: VisibleObject(3, "red van", "van", ("truck",)), 1: VisibleObject(1, "gate", "gate", target=False)},
                semantic_ids=rng.integers(0, 9, size=cam.shape, dtype=np.uint16),
            )
        T_world_body = body_transform(rng.normal(size=3) * 10, rng.uniform(-np.pi, np.pi), 0.1, -0.05)
        mount = T_BODY_CAM.copy()
        mount[:3, 3] = [0.1, 0.0, -0.02]
        out.append(
            Observation(
                t_s=0.1 * k + rng.uniform(0, 1e-3),
                rgb=rng.integers(0, 256, size=(*cam.shape, 3), dtype=np.uint8),
                depth_m=depth,
                T_world_cam=cam_transform_from_body(T_world_body),
                camera=cam,
                frame_id=f"sim:{seed}:{k}",
                T_body_cam=mount if k % 2 else T_BODY_CAM,
                annotation=ann,
            )
        )
    return out


def assert_bit_equal(a: Observation, b: Observation) -> None:
    assert a.t_s == b.t_s and a.frame_id == b.frame_id and a.camera == b.camera
    for x, y in ((a.rgb, b.rgb), (a.depth_m, b.depth_m), (a.T_world_cam, b.T_world_cam), (a.T_body_cam, b.T_body_cam)):
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()


@pytest.mark.parametrize("encoding", ["zlib", "raw"])
def test_round_trip_is_bit_for_bit(tmp_path, encoding):
    obs = random_observations(5, seed=1, annotated=True)
    with LogWriter(tmp_path / "log", LogWriterConfig(encoding=encoding), meta={"run": "test", "seed": np.int64(1)}) as w:
        for o in obs:
            w.write(o)
    reader = LogReader(tmp_path / "log")
    assert reader.meta["user"] == {"run": "test", "seed": 1}
    assert reader.meta["closed"] is True and reader.meta["frames"] == 5
    assert len(reader) == 5
    got = list(reader)
    for a, b in zip(got, obs):
        assert_bit_equal(a, b)
        assert a.annotation.objects == b.annotation.objects
        for name in ("instance_ids", "depth_m", "semantic_ids"):
            x, y = getattr(a.annotation, name), getattr(b.annotation, name)
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
    assert list(reader) and len(list(reader)) == 5  # iterating again starts over


def test_real_kitchen_frames_round_trip(tmp_path):
    frames = list(islice(TumReader(KITCHEN), 3))
    with LogWriter(tmp_path / "log") as w:
        for o in frames:
            w.write(o)
    for a, b in zip(LogReader(tmp_path / "log"), frames):
        assert_bit_equal(a, b)
        assert a.annotation is None
    # zlib keeps a real frame well under its 2.1 MB of raw arrays
    assert (tmp_path / "log" / "frames.bin").stat().st_size < 3 * 1.6e6


def test_events_round_trip_and_attach_to_frames(tmp_path):
    obs = random_observations(2)
    with LogWriter(tmp_path / "log") as w:
        assert w.event("task", {"instruction": "fly to the red van"}) == 0
        w.write(obs[0])
        w.event("decision", {"prompt": "where?", "raw": "[12, 7]", "pixel": np.array([12.0, 7.0]), "score": np.float32(0.5)})
        w.write(obs[1])
        w.event("verifier", {"moved_px": float("nan"), "gated": False}, t_s=9.5, frame_index=0)
    ev = list(LogReader(tmp_path / "log").events())
    assert [(e.seq, e.kind, e.frame_index) for e in ev] == [(0, "task", None), (1, "decision", 0), (2, "verifier", 0)]
    assert ev[0].t_s == 0.0 and ev[1].t_s == obs[0].t_s and ev[2].t_s == 9.5
    assert ev[1].data == {"prompt": "where?", "raw": "[12, 7]", "pixel": [12.0, 7.0], "score": 0.5}
    assert np.isnan(ev[2].data["moved_px"])


def test_event_data_that_is_not_json_is_refused(tmp_path):
    with LogWriter(tmp_path / "log") as w:
        with pytest.raises(LogError, match=r"event data of type object cannot be written as JSON"):
            w.event("x", {"thing": object()})
        with pytest.raises(LogError, match=r"event kind must be a non-empty string"):
            w.event("", {})


def test_log_is_readable_while_it_grows(tmp_path):
    obs = random_observations(3)
    w = LogWriter(tmp_path / "log")
    reader = LogReader(tmp_path / "log")
    assert len(reader) == 0 and list(reader) == []
    w.write(obs[0])
    assert [o.frame_id for o in reader] == [obs[0].frame_id]
    w.write(obs[1])
    w.event("status", {"s": "CONTINUE"})
    assert len(reader) == 2 and [e.kind for e in reader.events()] == ["status"]
    assert reader.meta["closed"] is False
    w.close()
    w.close()  # idempotent
    with pytest.raises(LogError, match=r"log writer is closed"):
        w.write(obs[2])


def _record_offsets(frames_bin: Path) -> list[int]:
    data = frames_bin.read_bytes()
    offsets, pos = [], len(FILE_MAGIC)
    while pos < len(data):
        offsets.append(pos)
        _, h, p = struct.unpack_from("<4sIQ", data, pos)
        pos += PREFIX_SIZE + h + p
    return offsets


@pytest.mark.parametrize("cut", ["in_prefix", "in_header", "in_payload", "one_byte_short"])
def test_truncated_log_reads_up_to_its_last_whole_frame(tmp_path, cut):
    obs = random_observations(4, seed=2)
    with LogWriter(tmp_path / "log") as w:
        for o in obs:
            w.write(o)
        w.event("a", {})
    frames_bin = tmp_path / "log" / "frames.bin"
    data = frames_bin.read_bytes()
    last = _record_offsets(frames_bin)[-1]
    end = {"in_prefix": last + 10, "in_header": last + PREFIX_SIZE + 5, "in_payload": last + (len(data) - last) // 2, "one_byte_short": len(data) - 1}[cut]
    frames_bin.write_bytes(data[:end])
    # the events file was cut mid-line too: the unfinished line is ignored
    events = tmp_path / "log" / "events.jsonl"
    events.write_bytes(events.read_bytes() + b'{"seq": 1, "t_s"')
    reader = LogReader(tmp_path / "log")
    got = list(reader)
    assert len(got) == 3 and len(reader) == 3
    for a, b in zip(got, obs):
        assert_bit_equal(a, b)
    assert [e.kind for e in reader.events()] == ["a"]


def test_zero_filled_tail_counts_as_unfinished(tmp_path):
    obs = random_observations(2)
    with LogWriter(tmp_path / "log") as w:
        for o in obs:
            w.write(o)
    frames_bin = tmp_path / "log" / "frames.bin"
    with open(frames_bin, "ab") as f:
        f.write(bytes(5000))
    assert len(list(LogReader(tmp_path / "log"))) == 2


def test_corrupt_frame_names_file_offset_and_index(tmp_path):
    obs = random_observations(3)
    with LogWriter(tmp_path / "log") as w:
        for o in obs:
            w.write(o)
    frames_bin = tmp_path / "log" / "frames.bin"
    offsets = _record_offsets(frames_bin)
    data = bytearray(frames_bin.read_bytes())
    data[offsets[1] + PREFIX_SIZE + 40] ^= 0xFF  # a byte inside frame 1's header/payload
    frames_bin.write_bytes(bytes(data))
    reader = LogReader(tmp_path / "log")
    it = iter(reader)
    assert_bit_equal(next(it), obs[0])
    with pytest.raises(LogCorruptError, match=rf"frames\.bin: corrupt frame record 1 at byte offset {offsets[1]}: body CRC mismatch") as info:
        next(it)
    assert info.value.frame_index == 1 and info.value.offset == offsets[1]
    # a damaged length field is corruption, not truncation (the prefix CRC catches it)
    data = bytearray(frames_bin.read_bytes())
    data[offsets[1] + 40] ^= 0xFF
    data[offsets[2] + 6] ^= 0x01
    frames_bin.write_bytes(bytes(data))
    with pytest.raises(LogCorruptError, match=rf"record 2 at byte offset {offsets[2]}: bad record marker or prefix CRC"):
        list(LogReader(tmp_path / "log"))


def test_not_a_log_errors_name_the_file(tmp_path):
    with pytest.raises(LogFormatError, match=r"nope: not a directory"):
        LogReader(tmp_path / "nope")
    d = tmp_path / "d"
    d.mkdir()
    with pytest.raises(LogFormatError, match=r"meta\.json: missing"):
        LogReader(d)
    (d / "meta.json").write_text("{not json")
    with pytest.raises(LogFormatError, match=r"meta\.json: not valid JSON"):
        LogReader(d)
    (d / "meta.json").write_text(json.dumps({"format": "onfly-log", "version": 99}))
    with pytest.raises(LogFormatError, match=r"unsupported version 99"):
        LogReader(d)
    (d / "meta.json").write_text(json.dumps({"format": "onfly-log", "version": 1}))
    (d / "frames.bin").write_bytes(b"PNG....12345")
    with pytest.raises(LogFormatError, match=r"frames\.bin: wrong file magic"):
        LogReader(d)
    (d / "events.jsonl").write_text('{"seq": 0, "t_s": 0, "kind": "a"}\nnot json\n')
    # a file header not yet (fully) written is a log with no frames yet, not an error
    for partial in (b"", FILE_MAGIC[:5]):
        (d / "frames.bin").write_bytes(partial)
        assert len(LogReader(d)) == 0 and list(LogReader(d)) == []
    with pytest.raises(LogFormatError, match=r"events\.jsonl:2: malformed event line"):
        list(LogReader(d).events())


def test_writer_never_overwrites(tmp_path):
    (tmp_path / "log").mkdir()
    (tmp_path / "log" / "keep.txt").write_text("x")
    with pytest.raises(LogExistsError, match=r"directory is not empty"):
        LogWriter(tmp_path / "log")
    with pytest.raises(ValueError, match=r"LogWriterConfig\.encoding must be one of"):
        LogWriterConfig(encoding="png")
