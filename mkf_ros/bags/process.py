"""Offline estimation over a bag, without DDS: what ``mkf process`` runs.

The IMU and magnetometer messages are fed, in the order they were recorded, to the same
:class:`mkf_ros.stream.adapter.StreamAdapter` the ``estimator`` node wraps, with the node's
conversions: a field whose covariance[0] is -1 is "not reported"; the output ``imu/data`` message
keeps the input's header, carries the filter's orientation and covariance, and fills the angular
velocity and linear acceleration like the node (``mkf_ros.ros.convert.fill_imu``). So a bag
processed here and the same bag replayed through the node give the same messages.

Bulk work (reading, decoding, encoding, writing) is vectorised (see :mod:`mkf_ros.bags.cdr`);
the adapter runs the whole recording in compiled code (:meth:`StreamAdapter.process`, in chunks
for the progress bar), with the results of the node's message-by-message calls.

A pass over the bag (:class:`_BagPass`) reads as its phases: the options checked
(:func:`_stream_params`, :func:`_check_smoothing`), the topics resolved (:meth:`_BagPass.topics`),
the set-up (:meth:`_BagPass.set_up`: smoothing, scoring, progress), the window loop
(:meth:`_BagPass.window`, :meth:`_BagPass.emit`), the end of the bag and the final checks
(:meth:`_BagPass.finish`, :meth:`_BagPass.check`). The messages are in
:mod:`mkf_ros.bags.messages`, the scoring against a ground-truth topic in
:mod:`mkf_ros.bags.scoring`, ``--smooth`` in :mod:`mkf_ros.bags.smoothing`.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.bags import cdr
from mkf_ros.bags.messages import Chunk, Outputs, decode, encode_outputs, run_stream
from mkf_ros.bags.reader import BagError, BagReader, normalize_topic
from mkf_ros.bags.scoring import Scorer, Scores
from mkf_ros.bags.smoothing import Capture, NullWriter, Smoothing, TwoWay, temp_files_error
from mkf_ros.bags.writer import BagWriter

#: IMU messages per window of the streaming pass (about 35 MB of messages in flight)
WINDOW_MESSAGES = 50_000


@dataclass
class ProcessResult:
    out: Path
    imu_topic: str
    mag_topic: str | None
    n_imu: int
    n_mag: int
    n_out: int
    params: dict[str, Any]
    counters: dict[str, int]
    timings: dict[str, float]
    outputs: Outputs | None  #: every estimate (``keep_outputs``), else None
    stamps: np.ndarray | None  #: (M,) s, output stamps (``keep_outputs``)
    log_s: np.ndarray | None  #: (M,) s since the bag start, output log times (``keep_outputs``)
    scores: Scores | None
    notes: list[str]
    accel_topic: str | None = None  #: split input: the accelerometer topic (imu_topic: gyro)
    n_accel: int = 0


@dataclass(frozen=True)
class ProcessOptions:
    """The keyword options of :func:`process_bag` (see there)."""

    imu_topic: str | None = None
    mag_topic: str | None = None
    accel_topic: str | None = None
    gyro_topic: str | None = None
    truth_topic: str | None = "imu/ground_truth"
    output_topic: str = "imu/data"
    storage: str = "mcap"
    overwrite: bool = False
    copy_input: bool = False
    skip: float = 0.0
    progress: Any = None
    window: int | None = WINDOW_MESSAGES
    keep_outputs: bool = False
    smooth: bool | str = False
    smooth_window: int | None = None
    smooth_overlap: int | None = None


def stream_param_names() -> list[str]:
    """Parameters that matter offline: the filter's and the node's input/time/output ones."""
    from mkf_ros.core.params import PARAMS

    return [p.name for p in PARAMS
            if p.scope == "filter" or (p.group in ("node: input and time", "node: output")
                                       and p.name != "publish_debug_topics")]


def process_bag(bag: str | Path, out: str | Path, params: Mapping[str, Any] | None = None,
                **options: Any) -> ProcessResult:
    """Run the estimator over ``bag`` and write ``out`` (see the module docstring).

    ``params``: filter and node parameters by name (ValueError if invalid). ``options``: the
    fields of :class:`ProcessOptions` (TypeError for any other keyword). ``progress``: a
    factory ``(description, total) -> callable(increment)`` or None. Raises :class:`BagError`
    for unusable input; the output bag is written only if everything succeeded.

    Topics: ``imu_topic`` None finds the IMU: the bag's only ``sensor_msgs/Imu`` topic, or
    ``imu/data_raw`` among several (otherwise an error lists them with their message counts);
    with ``use_mag``, ``mag_topic`` None likewise takes the only ``MagneticField`` topic (or
    ``imu/mag``). ``accel_topic`` and ``gyro_topic`` (both, and no ``imu_topic``) select split
    input (``input_mode`` split): separate accelerometer and gyro ``Imu`` streams, the output
    one message per gyro message. ``truth_topic`` (a ``QuaternionStamped`` topic, if the bag
    has it): the outputs are scored against it (``skip``: not the first seconds).
    ``output_topic``, ``storage`` (mcap or sqlite3), ``overwrite``, ``copy_input`` (the input
    topics are copied into ``out`` too): the output bag.

    Streaming: the bag is read, filtered, written and scored in windows of log time of about
    ``window`` messages (:meth:`BagReader.read_windows`; None: the whole bag as one window),
    the adapter's state carried from one to the next, so memory does not grow with the
    recording and the output does not depend on ``window``. ``keep_outputs``: also return
    every estimate (:class:`Outputs`, ``stamps``, ``log_s``; memory grows with the bag).

    ``smooth``: the output carries the fixed-interval smoother's orientation and covariance
    (docs/math.md §11; MEKF or MUKF) instead of the filter's: every filter step of the stream
    is recorded, smoothed in windows of ``smooth_window`` steps with ``smooth_overlap`` more
    (defaults as :func:`~mkf_ros.core.smoother.window_sizes`, at the IMU topic's mean rate:
    its messages over the bag's duration)
    and the messages are written once smoothed: memory and the output's delay are bounded by
    one smoothing window + overlap plus the bag windows they span. The other fields are the
    filter's as without it. ``smooth="two-way"``: that smoother's tilt fused with the same
    smoother's over the recording reversed (docs/math.md §11.5, as ``mkf_ros.estimate(...,
    smooth="two-way")``), in three passes: the bag read once to spill every filter step's
    readings to a file beside ``out`` (80 bytes per step), the reversed smoother over that
    file (its rows to a second file, 113 bytes per step), the bag read again and smoothed as
    above with each window's rows fused with the reversed ones; the files are removed at the
    end. Memory as above; disk about 0.2 KB per step.
    """
    from mkf_ros.core import smoother as sm_core

    opts = ProcessOptions(**options)
    try:
        mode = sm_core.smooth_mode(opts.smooth)
    except ValueError as e:
        raise BagError(str(e)) from None
    opts = replace(opts, smooth=mode is not None)
    bag, out = Path(bag), Path(out)
    if mode != "two-way":
        return _run_bag(bag, out, params, opts)
    BagWriter.check(out, opts.storage, opts.overwrite)
    try:
        tmp_dir = tempfile.TemporaryDirectory(prefix=f".{out.name}.two-way-", dir=out.parent)
    except OSError as e:
        raise temp_files_error(out.parent, e) from None
    with tmp_dir as tmp:
        two = TwoWay(Path(tmp) / "steps")
        t0 = time.perf_counter()
        _run_bag(bag, out, params, replace(opts, truth_topic=None, copy_input=False,
                                           keep_outputs=False), two)
        try:
            two.reverse(Path(tmp) / "reversed", opts.progress)
        except OSError as e:
            raise temp_files_error(out.parent, e) from None
        seconds = time.perf_counter() - t0
        res = _run_bag(bag, out, params, opts, two)
    res.timings["two-way"] = seconds
    return res


def _run_bag(bag: Path, out: Path, params: Mapping[str, Any] | None, opts: ProcessOptions,
             two_way: TwoWay | None = None) -> ProcessResult:
    """:func:`process_bag`'s pass over the bag; ``two_way`` (with ``smooth``): the first pass
    of ``--smooth two-way`` (nothing written: every filter step's readings spilled,
    :class:`~mkf_ros.bags.smoothing.Capture`) while it has no reversed rows, else the last
    (smoothed rows fused)."""
    from mkf_ros.stream.adapter import StreamAdapter

    adapter = StreamAdapter(_stream_params(params, opts))
    _check_smoothing(adapter.params, opts)
    run = _BagPass(bag, out, adapter, opts, two_way)
    with BagReader(bag) as br:
        run.topics(br)
        run.set_up(br)
        with NullWriter() if run.capture else BagWriter(out, opts.storage,
                                                        overwrite=opts.overwrite) as w:
            run.open_output(w, br)
            for win in br.read_windows(run.read, opts.window, run.tick):
                run.emit_all(run.window(win))
            run.emit_all(run.finish())
            run.check()  # before the writer closes: a problem drops the output
            t0 = time.perf_counter()
        run.tm["write"] += time.perf_counter() - t0
    return run.result()


def _stream_params(params: Mapping[str, Any] | None, opts: ProcessOptions) -> dict[str, Any]:
    """The adapter's parameters: ``params`` with the input mode the topic options ask for
    (split input: ``accel_topic`` and ``gyro_topic``), and the smoother's forward-pass
    defaults with ``smooth``. BagError for options that exclude each other."""
    from mkf_ros.core import smoother as sm_core

    params = dict(params or {})
    if (opts.accel_topic is None) != (opts.gyro_topic is None):
        raise BagError("split input needs both --accel-topic and --gyro-topic (separate "
                       "accelerometer and gyroscope sensor_msgs/Imu topics)")
    if opts.accel_topic is not None:
        if opts.imu_topic is not None:
            raise BagError("--imu-topic (one combined IMU topic) and --accel-topic/--gyro-topic "
                           "(split input) exclude each other")
        if params.get("input_mode", "split") != "split":
            raise BagError("--accel-topic/--gyro-topic are split input: input_mode must be "
                           "split")
        params["input_mode"] = "split"
    elif params.get("input_mode") == "split":
        raise BagError("input_mode split needs --accel-topic and --gyro-topic")
    if opts.smooth:
        params = sm_core.forward_params(params)
    return params


def _check_smoothing(p: Mapping[str, Any], opts: ProcessOptions) -> None:
    """With ``smooth``: an algorithm the smoother has, and a valid window (before the bag is
    opened; the default overlap needs its rate, :meth:`_BagPass.set_up`)."""
    from mkf_ros.core import smoother as sm_core

    if not opts.smooth:
        return
    if p["algorithm"] not in ("mekf", "mukf"):
        raise BagError(f"--smooth needs algorithm mekf or mukf (the smoother is the MKFs'), "
                       f"not {p['algorithm']}")
    try:
        sm_core.check_window(opts.smooth_window, opts.smooth_overlap)
    except ValueError as e:
        raise BagError(str(e)) from None


@dataclass
class _BagPass:
    """One pass over a bag (see the module docstring): its phases and what they share."""

    bag: Path
    out: Path
    adapter: Any  #: the :class:`~mkf_ros.stream.adapter.StreamAdapter`
    opts: ProcessOptions
    two_way: TwoWay | None = None
    notes: list[str] = field(default_factory=list)
    tm: dict[str, float] = field(default_factory=lambda: {"read": 0.0, "filter": 0.0,
                                                          "write": 0.0})
    imu: str = ""  #: the IMU topic (split input: the gyro's)
    acc: str | None = None  #: split input: the accelerometer topic
    mag: str | None = None
    truth: str | None = None
    read: list[str] = field(default_factory=list)  #: the topics read
    smoothing: Smoothing | None = None
    capturing: Capture | None = None
    scorer: Scorer | None = None
    tick: Any = None  #: the progress callback, or None
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(
        ("imu", "acc", "mag", "out"), 0))
    orientation: bool = False  #: the input carries an orientation (an estimator's output?)
    kept: list[tuple[Outputs, np.ndarray, np.ndarray]] = field(default_factory=list)
    writer: Any = None
    conn: Any = None
    copies: dict[str, Any] = field(default_factory=dict)
    bag_start: int = 0
    t0: float = field(default_factory=time.perf_counter)

    @property
    def p(self) -> dict[str, Any]:
        return self.adapter.params

    @property
    def capture(self) -> bool:
        """The first pass of ``--smooth two-way``: nothing written."""
        return self.two_way is not None and self.two_way.rows is None

    def topics(self, br: BagReader) -> None:
        """Resolve the IMU (or gyro and accelerometer), magnetometer and ground-truth topics."""
        o = self.opts
        if o.accel_topic is not None:
            self.imu = br.resolve(o.gyro_topic or "", cdr.IMU.msgtype, role="gyroscope")
            self.acc = br.resolve(o.accel_topic, cdr.IMU.msgtype, role="accelerometer")
            if self.acc == self.imu:
                raise BagError(f"--accel-topic and --gyro-topic are the same topic {self.imu}; "
                               "for one combined IMU topic use --imu-topic")
        elif o.imu_topic is not None:
            self.imu = br.resolve(o.imu_topic, cdr.IMU.msgtype, role="IMU")
        else:
            self.imu = br.discover(cdr.IMU.msgtype, role="IMU", flag="--imu-topic",
                                   preferred="imu/data_raw")
        mags = br.of_type(cdr.MAGNETIC_FIELD.msgtype)
        if self.p["use_mag"]:
            self.mag = (br.resolve(o.mag_topic, cdr.MAGNETIC_FIELD.msgtype, role="magnetometer")
                        if o.mag_topic is not None else
                        br.discover(cdr.MAGNETIC_FIELD.msgtype, role="magnetometer",
                                    flag="--mag-topic", preferred="imu/mag"))
        elif mags:
            self.notes.append(f"{', '.join(mags)} in the bag but use_mag is false (pass "
                              "--use-mag to fuse it)")
        if o.truth_topic and normalize_topic(o.truth_topic) in br.topics:
            self.truth = br.resolve(o.truth_topic, cdr.QUATERNION_STAMPED.msgtype,
                                    role="ground-truth")

    def set_up(self, br: BagReader) -> None:
        """The smoothing (or ``--smooth two-way``'s capture), the topics to read, the scorer
        and the progress bar."""
        from mkf_ros.bags.synth import read_description
        from mkf_ros.core import smoother as sm_core

        o = self.opts
        if o.smooth:
            steps = br.topics[self.imu].count  # the gyro's in split input: one step each
            sizes = sm_core.window_sizes(o.smooth_window, o.smooth_overlap, sm_core.mean_period(
                (br.end_ns - br.start_ns) * 1e-9, steps))
            if self.two_way is not None and self.capture:
                self.two_way.sizes = sizes
                self.capturing = Capture(self.adapter, self.two_way)
            else:
                self.smoothing = Smoothing(self.adapter, *sizes, self.two_way, o.keep_outputs)
        want = [t for t in (self.imu, self.acc, self.mag, self.truth) if t]
        extra = list(br.topics) if o.copy_input else []
        self.read = list(dict.fromkeys(want + extra))
        self.copies = dict.fromkeys(extra)
        if o.copy_input and normalize_topic(o.output_topic) in br.topics:
            raise BagError(f"output topic {normalize_topic(o.output_topic)} is also in the "
                           "input bag; choose another --output-topic or drop --copy-input")
        self.bag_start = br.start_ns
        if self.truth:
            desc = read_description(self.bag) or {}
            self.scorer = Scorer(self.p["world_frame"], bool(self.p["use_mag"]), o.skip,
                                 desc.get("intervals"), br.topics[self.imu].count)
        if o.progress:
            self.tick = o.progress("forward pass" if self.capture else "process",
                                   br.work_total(self.read))
        self.tm["read"] += time.perf_counter() - self.t0

    def open_output(self, w: Any, br: BagReader) -> None:
        """The output topic and the copied input topics in the writer ``w``."""
        self.writer = w
        self.conn = w.add_topic(normalize_topic(self.opts.output_topic), cdr.IMU.msgtype)
        self.copies = {t: w.add_topic(t, br.topics[t].msgtype) for t in self.copies}

    def window(self, win: Mapping[str, Any]) -> list[Chunk]:
        """One window of the bag through the adapter: its output messages, encoded (a
        :class:`~mkf_ros.bags.messages.Chunk`); the chunks now ready to go out."""
        t0 = time.perf_counter()
        imu_b = win[self.imu]
        imu = decode(imu_b.data, cdr.IMU, self.imu, self.bag)
        acc = acc_b = mag = mag_b = None
        if self.acc:
            acc_b = win[self.acc]
            acc = decode(acc_b.data, cdr.IMU, self.acc, self.bag)
        if self.mag:
            mag_b = win[self.mag]
            mag = decode(mag_b.data, cdr.MAGNETIC_FIELD, self.mag, self.bag)
        truth = (decode(win[self.truth].data, cdr.QUATERNION_STAMPED, self.truth, self.bag)
                 if self.truth else None)
        t1 = time.perf_counter()
        self.tm["read"] += t1 - t0
        outs = run_stream(self.adapter, imu, imu_b.log_ns, mag, mag_b.log_ns if mag_b else None,
                          self.p, None, acc, acc_b.log_ns if acc_b else None)
        if len(imu_b):
            self.orientation = self.orientation or _carries_orientation(imu)
        t2 = time.perf_counter()
        self.tm["filter"] += t2 - t1
        out_log = imu_b.log_ns[outs.index]
        if self.scorer is not None and truth is not None and len(imu_b):
            self.scorer.shift((int(imu_b.log_ns[0]) - self.bag_start) * 1e-9)
        chunk = Chunk(outs, [] if self.capture else encode_outputs(imu, imu_b, outs), out_log,
                      imu.stamp_ns[outs.index], (out_log - self.bag_start) * 1e-9, truth,
                      win[self.truth].log_ns if self.truth else None,
                      [(c, win[t].log_ns, win[t].data) for t, c in self.copies.items()])
        outs.index = outs.index + self.counts["imu"]
        for key, batch in (("imu", imu_b), ("acc", acc_b), ("mag", mag_b)):
            self.counts[key] += len(batch) if batch else 0
        self.counts["out"] += len(outs.index)
        self.tm["write"] += time.perf_counter() - t2
        return [chunk] if self.smoothing is None else self.smoothing.ready(chunk, False)

    def emit_all(self, chunks: list[Chunk]) -> None:
        """Windows' messages out: written, scored, kept."""
        for c in chunks:
            t0 = time.perf_counter()
            self.writer.write_batch(self.conn, c.out_log, c.encoded)
            for cn, log_ns, data in c.copies:
                self.writer.write_batch(cn, log_ns, data)
            self.tm["write"] += time.perf_counter() - t0
            if self.scorer is not None and c.truth is not None and c.truth_log is not None:
                self.scorer.add(c.truth, c.truth_log, c.outs.quat, c.out_stamp, c.out_log,
                                c.log_s)
            if self.opts.keep_outputs:
                self.kept.append((c.outs, c.out_stamp * 1e-9, c.log_s))

    def finish(self) -> list[Chunk]:
        """The bag has ended: the capture's last steps spilled, or every step smoothed; the
        chunks that were still waiting."""
        if self.capturing is not None:
            self.capturing.finish()
        if self.smoothing is None:
            return []
        done = self.smoothing.ready(None, True)
        tw = self.smoothing.two_way
        if tw is not None and tw.fused != tw.n:  # (the output is dropped)
            raise RuntimeError(f"two-way smoothing: {tw.fused} steps fused of {tw.n} "
                               "captured (the two passes over the bag differ)")
        self.tm["smooth"] = self.smoothing.seconds
        self.tm["filter"] -= self.smoothing.paused  # (the event loop's pauses to smooth)
        return done

    def check(self) -> None:
        """The final checks: an input that gave no estimate, or one the adapter judged
        unusable, is a BagError (and the output bag is dropped: BagWriter is never
        half-written); a gyro-less input gets a note."""
        from mkf_ros.stream.adapter import REJECTIONS

        n_imu = self.counts["imu"]
        if n_imu == 0:
            raise BagError(f"IMU topic {self.imu} in {self.bag} has no messages")
        found = self.adapter.input_problems(self.imu, self.acc or "")
        if "gyro" in found:  # an estimate of the tilt alone; said, not refused
            self.notes.append(found.pop("gyro"))
        problems = list(found.values())
        if not problems and self.counts["out"] == 0:
            why = ", ".join(f"{v} {k}" for k, v in self.adapter.counters.items()
                            if v and k in (*REJECTIONS, "acc_missing", "acc_implausible"))
            problems = [f"no estimate from the {n_imu} messages of {self.imu}"
                        + (f" ({why})" if why else "")]
        if problems:
            raise BagError("; ".join(problems) + "; no output written")

    def result(self) -> ProcessResult:
        """The pass's result, its scores and notes."""
        from mkf_ros.stream.adapter import orientation_note

        if self.orientation:
            self.notes.append(orientation_note(self.imu))
        scores = None
        if self.scorer is not None:
            self.scorer.finish()
            scores = self.scorer.result()
            if scores is None:
                self.notes.append(f"no {self.truth} message has the stamp of an output; not "
                                  "scored")
        outputs, stamps, log_s = _join(self.kept) if self.opts.keep_outputs else (None, None,
                                                                                  None)
        c = self.counts
        return ProcessResult(out=self.out, imu_topic=self.imu, accel_topic=self.acc,
                             n_imu=c["imu"], n_accel=c["acc"], mag_topic=self.mag,
                             n_mag=c["mag"], n_out=c["out"], params=self.p,
                             counters=self.adapter.all_counters(), timings=self.tm,
                             outputs=outputs, stamps=stamps, log_s=log_s, scores=scores,
                             notes=self.notes)


def _carries_orientation(imu: cdr.Decoded) -> bool:
    """Whether the IMU messages carry an orientation (an estimator's output read as raw
    data?)."""
    from mkf_ros.stream.adapter import carries_orientation

    return bool(carries_orientation(imu.fields["orientation"],
                                    imu.fields["orientation_covariance"][:, 0]))


def _join(kept: list[tuple[Outputs, np.ndarray, np.ndarray]]
          ) -> tuple[Outputs, np.ndarray, np.ndarray]:
    """The estimates of every window as one :class:`Outputs` (``keep_outputs``)."""
    outs = Outputs(**{f.name: np.concatenate([getattr(k[0], f.name) for k in kept])
                      for f in fields(Outputs)})
    return outs, np.concatenate([k[1] for k in kept]), np.concatenate([k[2] for k in kept])
