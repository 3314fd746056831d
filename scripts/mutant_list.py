"""The curated mutants of ``make mutants`` (run by scripts/mutants.py).

Each is one exact snippet replacement in one file, named by what the bug does, with the tests
that should catch it (pytest node ids or paths, plus an optional ``-k`` expression). Kernel
mutants (``kernel=True``) stay on math lines inside kernel bodies, which change least when the
kernel call interface is reworked. When a snippet stops matching (someone edited the line), the
mutant is reported ``stale``: update ``old``/``new`` to the new spelling of the same bug.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Mutant:
    name: str
    file: str
    old: str
    new: str
    tests: tuple[str, ...]
    why: str = ""
    k: str | None = None
    kernel: bool = False


T = "tests/"
ONLINE = T + "service/test_online.py"

MUTANTS: list[Mutant] = [
    # ------------------------------------------------------------------ kernels (numba)
    Mutant(
        "gating-no-chi-square-gate",
        "labeler_service/labeling/kernels/gating.py",
        "        rs = radius + _SLACK\n",  # the slab, then the ellipsoid: both removed
        "        rs = np.inf\n        gate = np.inf\n",
        (T + "labeling/test_gating.py",),
        "every point is a candidate of every marker (the gate removed)",
        kernel=True,
    ),
    Mutant(
        "kalman-predict-backwards",
        "labeler_service/labeling/kernels/kalman.py",
        "            x[i, a] += dt * x[i, 3 + a]",
        "            x[i, a] -= dt * x[i, 3 + a]",
        (T + "labeling/test_labeler.py",),
        "the constant-velocity prediction runs backwards",
        k="interleaved",
        kernel=True,
    ),
    Mutant(
        "kalman-covariance-grows-on-update",
        "labeler_service/labeling/kernels/kalman.py",
        "    P[i, 0] = (1.0 - kp) * pp",
        "    P[i, 0] = (1.0 + kp) * pp",
        (T + "labeling/test_kernels.py",),
        "P = (I - K H) P with the sign of K flipped",
        k="factorised_kalman",
        kernel=True,
    ),
    Mutant(
        "kabsch-rotation-element-sign",
        "labeler_service/labeling/kernels/rigid.py",
        "    R[0, 1] = 2.0 * (q1 * q2 - q0 * q3)",
        "    R[0, 1] = 2.0 * (q1 * q2 + q0 * q3)",
        (T + "shoulder/test_triangles.py",),
        "the quaternion-to-matrix conversion has a wrong sign (R no longer a rotation)",
        k="unique_best",
        kernel=True,
    ),
    Mutant(
        "branch-and-bound-bound-too-tight",
        "labeler_service/labeling/kernels/fitting.py",
        "        acc += k + w * best_m",
        "        acc += w * best_m",
        (T + "labeling/test_kernels.py",),
        "the upper bound forgets the structure term: optimal assignments get pruned",
        k="branch_and_bound",
        kernel=True,
    ),
    # ------------------------------------------------------------------ labeler, training
    Mutant(
        "labeler-trains-on-scrambled-init-frames",
        "labeler_service/labeling/labeler.py",
        "        pos[lab[ok]] = pts[ok]\n        self._pending.append((t, pos))",
        "        pos[lab[ok]] = pts[ok][::-1]\n        self._pending.append((t, pos))",
        (T + "labeling/test_labeler.py",),
        "the training window stores points under the wrong labels",
        k="interleaved",
    ),
    Mutant(
        "training-distances-shrunk",
        "labeler_service/labeling/training.py",
        "        D = s1 / n\n",
        "        D = 0.8 * s1 / n\n",
        (T + "labeling/test_training.py",),
        "the structure model D (Eq. 1) is 20 % short",
    ),
    Mutant(
        "baseline-never-updates-last-position",
        "labeler_service/labeling/baseline.py",
        "        self._last[point_labels[hit]] = pts[hit]",
        "        self._last[point_labels[hit]] = self._last[point_labels[hit]]",
        (T + "labeling/test_baseline.py",),
        "the closest-point baseline keeps the init positions forever",
    ),
    # ------------------------------------------------------------------ service
    Mutant(
        "online-model-file-ignores-the-model",
        "labeler_service/labeling/registry.py",
        "        return Labeler.from_model(loaded, rate, config)",
        "        return Labeler(loaded.marker_names, rate, config)",
        (ONLINE,),
        "a stream started from a model file trains from its first frames instead",
        k="udp and model-file and inline",
    ),
    Mutant(
        "rate-inference-returns-the-period",
        "labeler_service/service/stream.py",
        "            return float(1.0 / np.median(dt[ok] / steps[ok]))",
        "            return float(np.median(dt[ok] / steps[ok]))",
        (ONLINE,),
        "frame-rate inference from init frames returns seconds per frame",
        k="udp and init-frames and inline",
    ),
    Mutant(
        "init-frames-fed-without-labels",
        "labeler_service/service/stream.py",
        "            labeler.process(f.points, f.t, remap[idx])  # -1 stays -1",
        "            labeler.process(f.points, f.t, None)  # -1 stays -1",
        (T + "service/test_server.py",),
        "the buffered init frames reach the labeler unlabeled",
        k="starts_from_labeled_init_frames",
    ),
    Mutant(
        "duplicate-seq-accepted",
        "labeler_service/service/continuity.py",
        '        if ds == 0:\n            return Verdict("duplicate")',
        "        if ds == 0:\n            return Verdict(None, 0)",
        (T + "service/test_server.py",),
        "a repeated seq is labeled again",
        k="duplicate",
    ),
    Mutant(
        "restarted-sender-refused",
        "labeler_service/service/continuity.py",
        "            if c.count >= self.confirm:",
        "            if c.count >= 10**9:",
        (T + "service/test_server.py",),
        "a sender that restarts at seq 0 is dropped as late forever",
        k="restarted",
    ),
    Mutant(
        "init-overflow-not-counted",
        "labeler_service/service/server.py",
        '                self.metrics.drop("init_overflow", state.name)',
        '                self.metrics.drop("init_overflow", state.name, 0)',
        (T + "service/test_drops.py",),
        "init frames beyond max_init_frames vanish uncounted",
    ),
    Mutant(
        "output-oversize-not-counted",
        "labeler_service/service/server.py",
        '                self.metrics.drop("output_oversize", stream)',
        '                self.metrics.drop("output_oversize", stream, 0)',
        (T + "service/test_drops.py",),
        "labeled frames too large for a datagram vanish uncounted",
    ),
    Mutant(
        "model-message-not-sent-before-labeled-frames",
        "labeler_service/service/server.py",
        "            if self._published_model.get(state.name) != state.model_id:",
        "            if False:",
        (T + "service/test_server.py",),
        "subscribers get labeled frames they cannot decode",
        k="starts_from_labeled_init_frames",
    ),
    Mutant(
        "labeling-thread-setting-ignored",
        "labeler_service/service/server.py",
        "        if self.settings.labeling_thread:\n            self._executors[name]",
        "        if False:\n            self._executors[name]",
        (T + "service/test_server.py",),
        "labeling_thread = true still labels on the event loop",
        k="labeling_thread_setting",
    ),
    Mutant(
        "kernel-warm-up-skipped",
        "labeler_service/service/server.py",
        "            if self.settings.warmup:\n                log.info(\"warming up",
        "            if False:\n                log.info(\"warming up",
        (T + "service/test_server.py",),
        "the service reports ready before compiling its kernels",
        k="warmup_runs_before_ready",
    ),
    Mutant(
        "queue-full-not-counted",
        "labeler_service/service/server.py",
        "        if self._queues[msg.stream].put((msg, inc.recv_ns, verdict)) is not None:",
        "        if self._queues[msg.stream].put((msg, inc.recv_ns, verdict)) is None:",
        (T + "service/test_server.py",),
        "drops of the drop-oldest queue are miscounted",
        k="falling_behind",
    ),
    Mutant(
        "queue-drops-the-newest",
        "labeler_service/service/transports/base.py",
        "            old = self._items.popleft()",
        "            old = self._items.pop()",
        (T + "service/test_server.py",),
        "a full queue discards the newest frame instead of the oldest",
        k="falling_behind",
    ),
    Mutant(
        "mqtt-gives-up-reconnecting",
        "labeler_service/service/transports/mqtt.py",
        "            backoff = min(backoff * 2, self.settings.reconnect_max_s)",
        "            backoff = 1e6",
        (T + "service/test_mqtt.py",),
        "after a failed reconnect the service waits (practically) forever",
        k="broker_restart",
    ),
    Mutant(
        "non-finite-check-skips-rows",
        "labeler_service/service/protocol.py",
        "    if not np.isfinite(points).all():",
        "    if not np.isfinite(points[1:]).all():",
        (T + "service/test_protocol.py", T + "service/test_drops.py"),
        "a NaN in the first point passes validation",
    ),
    Mutant(
        "labels-length-unchecked",
        "labeler_service/service/protocol.py",
        "        if not isinstance(labels, list) or len(labels) != len(points):",
        "        if not isinstance(labels, list):",
        (T + "service/test_protocol.py",),
        "a frame with fewer labels than points is accepted",
    ),
    # ------------------------------------------------------------------ capture
    Mutant(
        "c3d-writer-residual-zero-for-missing",
        "labeler_service/capture/io.py",
        "    residuals[0, np.isnan(pts[0])] = -1.0",
        "    residuals[0, np.isnan(pts[0])] = 0.0",
        (T + "capture/test_c3d_missing.py",),
        "missing samples are written as valid (residual 0) for other tools",
    ),
    Mutant(
        "c3d-reader-ignores-negative-residuals",
        "labeler_service/capture/io.py",
        "        neg = residuals[0].T < 0",
        "        neg = residuals[0].T < -1e30",
        (T + "capture/test_c3d_missing.py",),
        "samples marked invalid by their residual are read as captured",
    ),
    Mutant(
        "zero-samples-kept",
        "labeler_service/capture/io.py",
        "    zero = np.all(pos == 0.0, axis=2)",
        "    zero = np.all(pos == 0.0, axis=2) & False",
        (T + "capture/test_io.py",),
        "(0, 0, 0) samples are not mapped to missing",
        k="zero_samples",
    ),
    Mutant(
        "y-up-rotation-mirrors",
        "labeler_service/capture/io.py",
        "    rotated = np.stack([x, -z, y], axis=-1)",
        "    rotated = np.stack([x, z, y], axis=-1)",
        (T + "capture/test_io.py",),
        "the Y-up to Z-up conversion is a reflection, not a rotation",
        k="y_up",
    ),
    Mutant(
        "metres-scaled-wrong",
        "labeler_service/capture/io.py",
        '**dict.fromkeys(("m", "meter", "meters", "metre", "metres"), 1000.0),',
        '**dict.fromkeys(("m", "meter", "meters", "metre", "metres"), 100.0),',
        (T + "capture/test_io.py",),
        "files in metres come out 10x too small",
        k="metres",
    ),
    # ------------------------------------------------------------------ tools
    Mutant(
        "recorder-writes-the-period-as-rate",
        "labeler_service/tools/subscribe.py",
        "            return round(1.0 / float(np.median(self._steps)), 3)",
        "            return round(float(np.median(self._steps)), 3)",
        (T + "tools/test_tools.py",),
        "the subscriber's C3D recording carries a wrong rate",
        k="recorder",
    ),
    # ------------------------------------------------------------------ evaluation
    Mutant(
        "baseline-accuracy-is-the-first-method",
        "labeler_service/evaluation/scoring.py",
        '        scores["closest-point"].summary()["accuracy"] if "closest-point" in scores',
        '        first.summary()["accuracy"] if "closest-point" in scores',
        (T + "evaluation/test_evaluate.py",),
        "baseline_accuracy reports the labeler's own accuracy",
        k="apart",
    ),
    Mutant(
        "scoring-counts-the-init-window",
        "labeler_service/evaluation/scoring.py",
        "        if f < self.init_frames:\n            self._seen[truth[real]] = True",
        "        if f < 0:\n            self._seen[truth[real]] = True",
        (T + "evaluation/test_evaluate.py",),
        "the supervised init frames count as correctly labeled",
    ),
    Mutant(
        "recovery-error-against-the-previous-frame",
        "labeler_service/evaluation/scoring.py",
        "removed, positions = stream.removed[f], stream.positions[f]",
        "removed, positions = stream.removed[f], stream.positions[max(f - 1, 0)]",
        (T + "evaluation/test_evaluate.py",),
        "recovery errors are measured against the wrong frame's truth",
    ),
    # ------------------------------------------------------------------ offline (shoulder)
    Mutant(
        "shoulder-acceptance-always-passes",
        "offline/shoulder/evaluation.py",
        '"pass": e[4] <= 0.85 * e[3],',
        '"pass": True,',
        (T + "shoulder/test_mg03.py",),
        "the e4 <= 0.85 e3 rule can no longer fail",
        k="acceptance",
    ),
    Mutant(
        "shoulder-e5-rule-always-passes",
        "offline/shoulder/evaluation.py",
        '"pass": rel <= 0.05,',
        '"pass": True,',
        (T + "shoulder/test_mg03.py",),
        "the abs(e5 - e4) <= 5 % e4 rule can no longer fail",
        k="acceptance",
    ),
    Mutant(
        "shoulder-mg03-rule-always-passes",
        "offline/shoulder/evaluation.py",
        '"pass": e[4] < m,',
        '"pass": True,',
        (T + "shoulder/test_mg03.py",),
        "the ours(4) < MG03 rule can no longer fail",
        k="acceptance",
    ),
    Mutant(
        "mg03-halfway-bone-at-the-elbow",
        "offline/shoulder/model.py",
        "        return mg03_bones(R, t, sk.chain_, sk.joints_[first])",
        "        return mg03_bones(R, t, sk.chain_, sk.joints_[sk.chain_[2]])",
        (T + "shoulder/test_mg03.py",),
        "MG03's halfway bone pivots at the wrong joint",
        k="halfway",
    ),
    Mutant(
        "mg03-halves-the-wrong-segment",
        "offline/shoulder/synthesis.py",
        "    Rh = half_rotation(R[:, root], R[:, first])",
        "    Rh = half_rotation(R[:, root], R[:, order[2]])",
        (T + "shoulder/test_mg03.py",),
        "MG03 halves the trunk-to-forearm rotation instead of the shoulder's",
        k="halfway",
    ),
    Mutant(
        "rest-pose-least-visible-frame",
        "offline/shoulder/triangles.py",
        "    frame = int(np.argmax(vis.sum(axis=1)))",
        "    frame = int(np.argmin(vis.sum(axis=1)))",
        (T + "shoulder/test_triangles.py",),
        "the rest pose is the frame with the fewest visible markers",
        k="rest_pose",
    ),
    Mutant(
        "joint-centre-equation-sign",
        "offline/shoulder/joints.py",
        "    b = tc[ok] - tp[ok]  # (F, 3)",
        "    b = tp[ok] - tc[ok]  # (F, 3)",
        (T + "shoulder/test_steps.py",),
        "the fixed-point equations of the joint centre have the translation flipped",
        k="joint_centre",
    ),
    Mutant(
        "boot-free-reading-without-the-window",
        "labeler_service/labeling/boot_match.py",
        "        if hist is not None and not (along is not None and along > FREE_READ_NATS):",
        "        if False:",
        (T + "labeling/test_boot_free_readings.py",),
        "a segment is moved onto free points on one frame's fit, the window not asked",
        k="window",
    ),
    Mutant(
        "boot-extension-no-free-reading",
        "labeler_service/labeling/boot.py",
        "            _free_readings(tpl, read, pts, out < 0, tree, hist, min_placed=3)",
        "            pass",
        (T + "labeling/test_boot_free_readings.py",),
        "the extension no longer reads a booted subject's segments again onto free points",
        k="extension",
    ),
]
