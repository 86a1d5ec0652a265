"""The per-frame pipeline: preprocess -> pose -> fuse -> ray cast -> transfer R_TR -> solve F.

Every stage is timed; timings travel with the FrameResult. Lighting samples are the pixels
(r*stride, c*stride); the observed radiance there is a box average centred on the pixel (less
noise at no extra cost) and a sample is used only when its whole box is usable and the fused surface agrees with
the frame's depth (preprocess.strided_box and lighting.samples on the CPU, kernels.samples on a GPU). The
solve also takes samples of earlier views (photoreg.lighting.history, lighting.history).

With lighting.asynchronous the estimate (samples, transfer, solve, traced light, history, filter) runs in one worker
thread beside the frames: each frame holds the latest finished estimate, as between estimates with lighting.every.
The worker alone touches the solve's state (history, filter, light search), since a new estimate starts only when
the last one is collected; the fused luminance map, which both use, is replaced whole by the worker's update
(ExposureTracker.map), so the frames read it without a lock. The worker traces the volume as the
frames fuse it meanwhile (the same CUDA stream serialises the two; on the CPU it may read a block half-updated).
With lighting.solve_process the worker hands its robust solves (pure functions of their samples) to a child
process, so the frames do not wait for the solve's interpreter lock.
"""
from __future__ import annotations

import copy
import dataclasses
import multiprocessing
import sys
import time
from concurrent import futures
from contextlib import contextmanager

import numpy as np

from .config import Session, validate
from .device import exit_with_parent, init_warp, keep_frame_memory, resolve_device
from .io.intrinsics import checked_intrinsics, checked_shutter
from .kernels.raycast import raycast_surface
from .kernels.samples import AGREES, CANDIDATE, CLIPPED, sample_maps
from .kernels.transfer import make_direction_set, radiance_transfer, visibility
from .lighting import sh
from .lighting.bounce import bounce_columns, observed_bounce_terms
from .lighting.exposure import ExposureTracker
from .lighting.history import Samples, SampleHistory
from .lighting.robust import Solution, Term, bounce_term, solve
from .lighting.samples import agreement
from .lighting.solver import SolverConfig
from .lighting.sun import Sun, SunConfig, SunSearch, disc_rays, sun_term
from .lighting.temporal import FilterConfig, LightingFilter
from .preprocess import Prepared, prepare, strided_box
from .recon.fusion import RESTART_AFTER, FusionConfig, TSDFVolume, VolumeLimitError
from .types import Frame, FrameResult, Intrinsics, Lighting, SolveDiagnostics

SAMPLE_SURPLUS = 1.5  # candidates checked per sample kept (the depth agreement test drops a few)
GAIN_SAMPLES = 2000   # samples of a frame that holds the lighting (lighting.every): only its exposure gain
BOX_LOSS = 0.5       # share of the usable surface pixels lost to incomplete sample boxes that the notes report
GAIN_STRIDE = 4       # ... ray cast up to this stride where nothing else needs the maps (Pipeline._gain_stride)


def _solve_process() -> futures.ProcessPoolExecutor:
    """A child process for the asynchronous worker's robust solves (lighting.solve_process), spawned (a fork would
    copy the CUDA context) and its imports done now, so the first estimate does not wait for them."""
    pool = futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=exit_with_parent)
    try:
        pool.submit(exec, "import photoreg.lighting.robust").result()
    except futures.BrokenExecutor as e:   # the child died starting (its own traceback is on stderr)
        pool.shutdown(wait=False, cancel_futures=True)
        raise RuntimeError(
            "the lighting's solve process (lighting.solve_process) could not start. A spawned child imports the "
            "main script again: a script that builds a Pipeline or runs a session at import needs "
            "`if __name__ == \"__main__\":` round that code; or set lighting.solve_process = false") from e
    return pool


class Pipeline:
    """One pipeline per recording/stream: owns (or shares) the volume, owns the direction set and the previous
    estimate."""

    def __init__(self, session: Session, intrinsics: Intrinsics, volume: TSDFVolume | None = None):
        """`volume`: a fusion volume to share (its owner fuses; see observe/estimate), else a new one. The session is
        checked as a session file's is (config.validate) and copied: changing it afterwards changes nothing here
        (before, some settings took effect and others did not, one of them crashing)."""
        session = copy.deepcopy(session)
        validate(session)
        intrinsics = checked_intrinsics(intrinsics.to_json(), "the pipeline's intrinsics")
        self.session = session
        self.intrinsics = intrinsics
        self._closed = False
        self.device = resolve_device(session.device)
        self._wp = init_warp()
        keep_frame_memory()
        rc, lc = session.reconstruction, session.lighting
        self.volume = volume if volume is not None else TSDFVolume(
            FusionConfig(voxel_size=rc.voxel_size, trunc_voxels=rc.trunc_voxels, depth_min=rc.depth_min,
                         depth_max=rc.depth_max, block_count=rc.block_count), self.device)
        self.solver_cfg = SolverConfig.from_lighting(lc)
        self.dirs, self.Y = make_direction_set(lc.rays, self.solver_cfg.fit_bands, seed=0)
        self.filter = (LightingFilter(self.solver_cfg.fit_bands,
                                      FilterConfig(lc.process_noise, lc.change_threshold, lc.new_view_share))
                       if lc.temporal else None)
        self.history = (SampleHistory(lc.history, seed=self.solver_cfg.seed, view_deg=lc.history_view_deg)
                        if lc.history else None)  # earlier views
        self.tracker = None
        if not session.recording.use_poses:
            from .recon.tracking import Tracker
            self.tracker = Tracker(self.volume, intrinsics, rc)
        self.prev_F: np.ndarray | None = None
        self.prev_from: tuple[int | None, dict | None] = (None, None)   # prev_F's estimated_frame and traced light
        self.last_solution: Solution | None = None  # the latest frame's solve (benchmarks/observability.py)
        # the latest estimate (frame index, lighting, diagnostics) and how many frames have held it (lighting.every)
        self._held: tuple[int, Lighting, SolveDiagnostics] | None = None
        self._held_for = 0
        # lighting.asynchronous: the worker, the estimate in flight (its frame index, the frames with a pose seen
        # when it started, its future) and the frames with a pose so far
        self._worker = (futures.ThreadPoolExecutor(1, thread_name_prefix="photoreg-lighting") if lc.asynchronous
                        else None)
        self._in_flight: tuple[int, int, futures.Future] | None = None
        self._frames = 0
        # the samples' box radiance and depth checks by one kernel over the maps on a GPU; on the CPU by OpenCV's box
        # filter and numpy over the candidates drawn, faster there (the same samples either way: kernels.samples);
        # the kernel linearises the 8-bit colour itself, so a denoised one (lighting.denoise) takes the host's path
        self.sample_kernel = self.device != "cpu" and lc.denoise == "none"
        # the last frame's per-pixel sample checks (prep, maps, sample_kernel, result): a frame that hands its estimate to the worker
        # (lighting.asynchronous) takes its gain's samples from the same maps first, and the worker reuses them
        self._checked: tuple | None = None
        self._solver = _solve_process() if lc.asynchronous and lc.solve_process else None
        # Extra terms (the bounce, the dominant light) only with fixed bands: order selection compares SH models.
        fixed = self.solver_cfg.select == "fixed"
        if not fixed and (lc.sun or lc.bounce):
            print(f"photoreg: lighting.select = {lc.select!r} compares SH models alone: the traced light "
                  "(lighting.sun) and the bounce term (lighting.bounce) are off", file=sys.stderr)
        self.bounce = lc.bounce and fixed
        self.observed_bounce = self.bounce and lc.bounce_observed
        # the fused surface luminance: the exposure gain's reference and what blocked rays see (observed bounce)
        self.surface = (ExposureTracker(cell=2 * rc.voxel_size) if lc.exposure or self.observed_bounce
                        else None)
        self.sun = (SunSearch(SunConfig(candidates=lc.sun_candidates, samples=lc.sun_samples,
                                         min_gain=lc.sun_min_gain, rays=lc.sun_rays,
                                         refine_every=lc.sun_refine_every))
                    if lc.sun and fixed else None)
        self.render = None  # virtual objects (issue 5): RenderStage, built before any frame
        if session.objects:
            from .render.stage import RenderStage
            self.render = RenderStage(session, intrinsics, self.device)

    @contextmanager
    def _timed(self, timings: dict, stage: str):
        t0 = time.perf_counter()
        yield
        if self.device != "cpu":
            self._wp.synchronize_device(self.device)
        timings[stage] = timings.get(stage, 0.0) + (time.perf_counter() - t0) * 1000.0  # a stage may come back

    def _pose(self, frame: Frame, prep: Prepared) -> tuple[np.ndarray | None, list[str]]:
        if self.tracker is not None:
            return self.tracker.track(frame, prep)
        if frame.pose is None:
            return None, [f"frame {frame.index}: no pose given (to track the camera instead: photoreg run --no-poses, "
                          "a session's recording.use_poses = false, a stream's hello options.track = true)"]
        return frame.pose, []

    def _samples(self, prep: Prepared, maps, pose: np.ndarray,
                 cap: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """Radiance (box average), world points, normals and whether the box holds clipped pixels alone
        (lighting.censored: a lower bound) at usable sample pixels (the maps' stride: lighting.stride, or GAIN_STRIDE
        for a held frame's gain) whose fused surface agrees with the frame's depth (photoreg.lighting.samples): at
        most `cap` (default lighting.max_samples) of them, a random subset as the solve would take. Only a surplus of
        candidates is checked, so the cost does not grow with the resolution (stride 1 at 640x480: 8000 samples of
        300000 pixels). Last, the share of the surface's usable pixels whose box is not whole (scattered depth holes
        empty boxes: the frame's notes say so)."""
        lc = self.session.lighting
        st = maps.stride
        gap = lc.max_depth_gap_voxels * self.session.reconstruction.voxel_size
        ws = maps.valid.shape[1]
        checked = self._checked
        if (checked is None or checked[0] is not prep or checked[1] is not maps
                or checked[2] != self.sample_kernel):
            checked = (prep, maps, self.sample_kernel,
                       strided_box(prep, st, lc.sample_box, lc.censored) if not self.sample_kernel else
                       sample_maps(prep.colour, prep.usable, prep.depth, self.intrinsics, pose, maps,
                                   lc.max_normal_angle, gap, self.device, lc.sample_box,
                                   prep.clipped if lc.censored else None))
            self._checked = checked   # one tuple, replaced whole: the worker and the frames read it without a lock
        if not self.sample_kernel:
            radiance, usable, clipped = checked[3]
            cand = np.flatnonzero(usable & maps.valid)

            def agrees(idx: np.ndarray) -> np.ndarray:
                r, c = np.divmod(idx, ws)
                return agreement(prep.depth, self.intrinsics, pose, r * st, c * st, maps.depth[r, c],
                                 maps.normal[r, c], max(2, st), lc.max_normal_angle, gap)
        else:
            radiance, flags = checked[3].radiance, checked[3].flags
            clipped = (flags & CLIPPED) > 0
            flags = flags.ravel()
            cand = np.flatnonzero(flags & CANDIDATE)

            def agrees(idx: np.ndarray) -> np.ndarray:
                return (flags[idx] & AGREES) > 0
        centre = prep.usable[::st, ::st] & maps.valid   # the sample pixels a box may keep (strided: no full-frame pass)
        if lc.censored:
            centre |= prep.clipped[::st, ::st] & maps.valid
        centre = np.count_nonzero(centre)
        lost = 1.0 - cand.size / centre if centre else 0.0
        cap = self.solver_cfg.max_samples if cap is None else cap
        rng = np.random.default_rng(self.solver_cfg.seed)
        if cap is not None and cand.size > cap * SAMPLE_SURPLUS:
            cand = np.sort(rng.choice(cand, int(cap * SAMPLE_SURPLUS), replace=False))
        ok = cand[agrees(cand)]
        if cap is not None and ok.size > cap:
            ok = np.sort(rng.choice(ok, cap, replace=False))
        r, c = np.divmod(ok, ws)
        return radiance[r, c], maps.vertex[r, c], maps.normal[r, c], clipped[r, c], lost

    def _traced(self, n: int) -> tuple[np.ndarray, int | None]:
        """Rows of the frame's n samples whose transfer is traced, and how many kept samples join them (None:
        all). Every row where the current view gets a solve of its own (no history yet, or the light search
        is due); else only the current view's share of what the joint solve draws (SampleHistory.draw): the
        rest would be traced for nothing (TUM at stride 4: 5700 of 7500 samples traced)."""
        if self.history is None or self._search_due():
            return np.arange(n), None
        return self.history.draw(n, self.solver_cfg.max_samples)

    def _gain_stride(self) -> int:
        """Ray-cast stride of a held frame with no render stage (only its exposure gain needs the maps): the
        lighting's, or coarser up to GAIN_STRIDE while the frame keeps GAIN_SAMPLES * SAMPLE_SURPLUS pixels at it
        (stride 1 at 640x480: 4; the full maps took 7.6-8.5 ms on the H100 beside the asynchronous worker)."""
        fit = int(np.sqrt(self.intrinsics.width * self.intrinsics.height / (GAIN_SAMPLES * SAMPLE_SURPLUS)))
        return max(self.session.lighting.stride, min(GAIN_STRIDE, fit))

    def _held_stride(self) -> int:
        """Ray-cast stride of a frame that holds the lighting: the render stage's (render.stride: its maps serve the
        exposure gain too) unless the gain needs a finer one (_gain_stride); without a render stage the gain's."""
        gain = self._gain_stride()
        if self.render is None or (self.session.lighting.exposure and self.render.stride > gain):
            return gain
        return self.render.stride

    def _search_due(self) -> bool:
        """Whether this frame searches the light (then the current view gets a solve of its own)."""
        return self.sun is not None and self.sun.due()

    def _terms(self, data: Samples) -> list[Term]:
        """The solve's extra terms other than the traced light: the bounce (lighting.bounce), split into observed
        and fitted radiance with lighting.bounce_observed."""
        if not self.bounce:
            return []
        if self.observed_bounce:
            return observed_bounce_terms(data.bounce, data.transfer, data.radiance)
        return [bounce_term(data.transfer, data.radiance)]

    def _solve(self, data: Samples, previous, terms: list[Term], grid=None, sun: Sun | None = None, start=None,
               current: int | None = None):
        """The robust solve of `data` with `terms` (self._terms(data)), and with the traced light `sun` (its
        disc traced through `grid` from every sample) when given; `start`: the solve of the same samples
        without it; `current`: how many of data's first rows are the current view's (data holds kept ones)."""
        lc = self.session.lighting
        terms = list(terms)
        cfg = self.solver_cfg
        if sun is not None:
            disc = disc_rays(sun, self.sun.cfg.rays).astype(np.float32)
            seen = visibility(grid, data.points, data.normals, disc, lc.ray_offset_voxels *
                              self.session.reconstruction.voxel_size, lc.ray_length)
            terms.append(sun_term(sun, seen, data.normals, disc, cfg.fit_bands))
            # the SH part of the joint solve holds only what the traced light leaves: regularised more (config.py)
            cfg = dataclasses.replace(cfg, regularization=lc.sun_regularization)
        args = (data.radiance, data.transfer, data.normals, data.visible, cfg)
        kwargs = dict(points=data.points, reference=previous, terms=terms, start=start, current=current,
                      clipped=data.clipped)
        if self._solver is not None:   # lighting.solve_process: the same function, in the child process
            try:
                return self._solver.submit(solve, *args, **kwargs).result()
            except futures.BrokenExecutor as e:   # the child died (BrokenProcessPool)
                raise RuntimeError("the lighting's solve process stopped (killed, or out of memory?); "
                                   "lighting.solve_process = false solves in the worker thread instead") from e
        return solve(*args, **kwargs)

    def _find_sun(self, grid, current: Samples, sol, terms: list[Term]) -> Sun | None:
        """The dominant light (photoreg.lighting.sun) from the current view's samples and their solve `sol`
        (with `terms`; None when no search is due)."""
        lc, rc = self.session.lighting, self.session.reconstruction
        offset = lc.ray_offset_voxels * rc.voxel_size

        def trace(idx, dirs):
            return visibility(grid, current.points[idx], current.normals[idx], dirs.astype(np.float32), offset,
                              lc.ray_length)

        def design(idx):
            return np.hstack([current.transfer[idx, :self.solver_cfg.fit_bands ** 2]] +
                             [t.transfer[idx, None] for t in terms])

        return self.sun(trace, sol, current.radiance, design, current.normals, current.points)

    def _lighting(self, grid, current: Samples, data: Samples, previous, t: dict[str, float]):
        """(sun, solution, the current view's own solve or None): the lighting of the samples `data` (the
        current view's, or those and the history's), jointly with the traced light when one is held. The light
        is searched from the current view's samples and their own solve (its shadows; the history's samples
        would dilute them); with a history that own solve runs only on frames the search is due (a coarse
        pass, or a held light refined); a held light whose joint fit is stale (SunSearch.stale) is refined in
        the frame after all."""
        with self._timed(t, "solve"):
            alone = data is current or self._search_due()   # else the search needs no solution (Sun.due)
            own_terms = self._terms(current) if alone else []
            own = self._solve(current, previous, own_terms) if alone else None
            terms = own_terms if data is current else self._terms(data)
        sun = None
        if self.sun is not None:
            with self._timed(t, "sun"):
                sun = self._find_sun(grid, current, own, own_terms)
        if sun is not None:
            with self._timed(t, "sun"):
                split = None if data is current else len(current)
                joint = self._solve(data, previous, terms, grid, sun, start=own if split is None else None,
                                    current=split)
            if "sun" in joint.terms:   # else no sample to fit it on (a black frame without a history)
                if self.sun.stale(joint.diagnostics.residual_rms) and not alone:
                    self.sun.recheck()
                    return self._lighting(grid, current, data, previous, t)
                if joint.terms["sun"] @ sh.LUMINANCE > 0:
                    return sun, joint, own
            sun = None
        if data is current:
            return sun, own, own
        with self._timed(t, "solve"):
            return sun, self._solve(data, previous, terms, current=len(current)), own

    def _estimate_lighting(self, index: int, prep: Prepared, maps, pose: np.ndarray, grid,
                           t: dict[str, float]) -> tuple[Lighting, SolveDiagnostics, float]:
        """(lighting, diagnostics, exposure gain) of frame `index`: samples, transfer, solve, traced light, history,
        temporal filter."""
        lc, rc = self.session.lighting, self.session.reconstruction
        with self._timed(t, "sample"):
            radiance, points, normals, clipped, lost = self._samples(prep, maps, pose)
        with self._timed(t, "transfer"):
            traced, kept = self._traced(len(points))
            offset = lc.ray_offset_voxels * rc.voxel_size
            tr = radiance_transfer(grid, points[traced], normals[traced], self.dirs, self.Y, offset=offset,
                                   ray_length=lc.ray_length, hit_distances=self.observed_bounce)
        with self._timed(t, "solve"):
            seen = ~clipped   # the exposure gain and the fused luminance from unsaturated colour alone
            gain = self.surface.gain(points[seen], radiance[seen])[0] if lc.exposure else 1.0
            bounce = (bounce_columns(tr, points[traced], normals[traced], self.dirs, offset, self.surface)
                      if self.observed_bounce else np.zeros((len(traced), 2)))
            current = Samples(radiance[traced] / gain, tr.transfer, normals[traced], points[traced],
                              tr.visible_fraction, bounce, clipped[traced])
            data = self.history.with_current(current, kept) if self.history is not None else current
            previous = self.filter.prediction() if self.filter is not None else self.prev_F
        sun, sol, own = self._lighting(grid, current, data, previous, t)
        self.last_solution = sol
        # nothing to fit a light on (a black frame without a history of samples): the solve returned the previous
        # lighting, and the previous frame's traced light stays with it (it was dropped: the frame's shadows fell back
        # to F's lobe, and the filtered irradiance started again at the next frame)
        keep_light = sun is None and sol.diagnostics.n_samples == 0 and self.prev_from[1] is not None
        with self._timed(t, "solve"):
            F, diag = sol.lighting, sol.diagnostics
            if sun is not None:
                diag.sun = {"direction": np.round(sun.direction, 6).tolist(), "angle": sun.angle,
                            "irradiance": np.round(sol.terms["sun"], 7).tolist(), "gain": round(sun.gain, 5)}
            if "bounce" in sol.terms:
                diag.bounce_radiance = np.round(sol.terms["bounce"], 7).tolist()
            if "bounce_observed" in sol.terms:
                diag.bounce_observed = np.round(sol.terms["bounce_observed"], 5).tolist()
            diag.exposure_gain, diag.estimated_frame = gain, index
            if lost > BOX_LOSS:   # real recordings lose 2-19% (edges); scattered holes nine in ten
                diag.notes.append(f"{lost:.0%} of the surface's usable pixels lost as samples: holes or masked pixels "
                                  f"in their {lc.sample_box or maps.stride | 1} px boxes (lighting.sample_box = 1 "
                                  "samples single pixels)")
            # the current view's samples its own solve fitted; without an own solve those the solve of the current
            # and kept samples fitted (the current view's rows come first; every usable sample instead cost TUM's
            # held-out residual 0.226 -> 0.238)
            fit = own if own is not None else sol
            rows = (np.zeros(0, dtype=np.int64) if fit.samples is None else
                    fit.samples[(fit.samples < len(current)) & (fit.weights > 0)])
            enough = rows.size >= self.solver_cfg.min_samples_factor * self.solver_cfg.fit_bands ** 2
            new_view = False   # whether the history took this frame's samples as a new view
            if self.history is not None and enough:
                new_view = self.history.add(current.take(rows), pose)
            elif self.history is not None and data is not current:  # a black, saturated or hole-ridden view
                diag.weak = True
                diag.notes.append("too few usable samples in this view: the lighting rests on earlier views' samples")
            if self.filter is not None and not enough and self.filter.prediction() is None:
                # the first filtered estimate is every later solve's reference, whose colour balance fixes their
                # albedo scale: a frame with a patch of depth started it and left the demo's later frames 29% dark
                diag.weak = True
                diag.notes.append("too few usable samples to start the temporal filter on: this frame's own estimate")
            elif self.filter is not None:
                filtered, diag.change_detected = self.filter.update(sol, new_view)
                if diag.change_detected and self.sun is not None:
                    self.sun.lighting_changed()
                # the filter weighs the channels apart: a white-mode light is one colour again
                F = Lighting(sh.one_chroma(filtered) if lc.mode == "white" else filtered)
                e = None if keep_light else self.filter.irradiance(None if sun is None else sol.terms["sun"],
                                                                   diag.change_detected,
                                                                   None if sun is None else sun.direction)
                if e is not None:   # the renderers draw the light with the filtered irradiance
                    diag.sun["irradiance_frame"] = diag.sun["irradiance"]
                    diag.sun["irradiance"] = np.round(e, 7).tolist()
            if keep_light:
                diag.sun = dict(self.prev_from[1])
                diag.notes.append(f"no samples: the traced light of frame {self.prev_from[0]} held")
            if self.surface is not None:
                self.surface.update(points[seen], radiance[seen] / gain)
        return F, diag, gain

    def _estimate_beside(self, index: int, prep: Prepared, maps, pose: np.ndarray, grid):
        """_estimate_lighting in the worker thread (lighting.asynchronous): (lighting, diagnostics, its stages' ms)."""
        t: dict[str, float] = {}
        F, diag, _ = self._estimate_lighting(index, prep, maps, pose, grid, t)
        return F, diag, t

    def _collect(self, t: dict[str, float]) -> None:
        """Hold the finished estimate of the worker (its error is raised here); its stages' ms go into t as
        'worker <stage>' (they ran beside the frames since it started)."""
        index, started, future = self._in_flight
        self._in_flight = None
        F, diag, worker_t = future.result()
        self._held = (index, F, dataclasses.replace(diag, notes=list(diag.notes)))
        self._held_for = self._frames - 1 - started   # frames after its own before this one, as lighting.every counts
        for stage, ms in worker_t.items():
            t["worker " + stage] = ms

    def wait_for_estimate(self) -> None:
        """Block until the estimate in flight (lighting.asynchronous) is done; the next frame then collects it (and
        raises its error). A replay that calls this after every frame gets the in-line estimates one frame later."""
        if self._in_flight is not None:
            futures.wait([self._in_flight[2]])

    def close(self) -> None:
        """Wait for the estimate in flight (lighting.asynchronous) and stop the worker and its solve process;
        idempotent. A closed pipeline processes no frame."""
        self._closed = True
        if self._worker is not None:
            self._worker.shutdown(wait=True)
            self._in_flight = None
        if self._solver is not None:
            self._solver.shutdown(wait=True)
            self._solver = None

    def _hold(self, prep: Prepared, maps, pose: np.ndarray,
              t: dict[str, float]) -> tuple[Lighting, SolveDiagnostics, float]:
        """(lighting, diagnostics, exposure gain) of a frame between estimates (lighting.every): the latest
        estimate, with this frame's exposure gain (the composite is in this frame's exposure)."""
        index, F, held = self._held
        gain = 1.0
        if self.session.lighting.exposure:
            with self._timed(t, "sample"):
                radiance, points, _, clipped, _ = self._samples(prep, maps, pose, GAIN_SAMPLES)
                gain = self.surface.gain(points[~clipped], radiance[~clipped])[0]
        note = (f"lighting of frame {index}, estimated beside the frames since (lighting.asynchronous)"
                if self._worker is not None else
                f"lighting of frame {index} held (lighting.every = {self.session.lighting.every})")
        diag = dataclasses.replace(held, notes=[note] + held.notes, exposure_gain=gain, change_detected=False)
        return Lighting(F.sh.copy()), diag, gain

    def process(self, frame: Frame) -> FrameResult:
        """Run every stage on one frame; a weak or empty frame still yields a finite estimate."""
        t: dict[str, float] = {}
        t_all = time.perf_counter()
        prep, pose, notes = self.observe(frame, t)
        return self.estimate(frame, prep, pose, notes, t, t_all)

    def observe(self, frame: Frame, t: dict[str, float]) -> tuple[Prepared, np.ndarray | None, list[str]]:
        """Preprocess, pose and fuse one frame (the stages that no lighting setting changes); ms into t."""
        if self._closed:
            raise RuntimeError("this Pipeline was closed: make a new one to process more frames")
        lc, rc = self.session.lighting, self.session.reconstruction
        k, own = frame.intrinsics, self.intrinsics   # the pipeline's are the ones every stage uses
        if k != own and not np.allclose([k.width, k.height, k.fx, k.fy, k.cx, k.cy],
                                        [own.width, own.height, own.fx, own.fy, own.cx, own.cy], rtol=1e-6, atol=1e-9):
            raise ValueError(f"frame {frame.index} ({frame.source}): its intrinsics {k} are not the pipeline's {own}")
        if frame.shutter is not None:
            checked_shutter(frame.shutter, f"frame {frame.index}")
        with self._timed(t, "preprocess"):
            prep = prepare(frame, lc, rc)
        with self._timed(t, "pose"):
            pose, notes = self._pose(frame, prep)
        if pose is not None:
            with self._timed(t, "fuse"):
                # prepare zeroed the depth below rc.depth_min: clean for a volume that drops no more (a shared one
                # may), unless the bilateral filter (which may dip just below it) ran
                restarts = self.volume.restarts
                try:
                    self.volume.integrate(prep.depth, self.intrinsics, pose,
                                          clean=rc.depth_min >= self.volume.cfg.depth_min and not rc.depth_filter_px)
                except VolumeLimitError as e:   # a wrong pose, as a rule: the frame counts as one without a pose
                    pose, notes = None, [*notes, f"frame {frame.index}: {e}"]
                if self.volume.restarts != restarts:
                    notes = [*notes, f"frame {frame.index}: the fused volume started again from this frame "
                                     f"({RESTART_AFTER} frames in a row did not fit with it: the earlier poses were "
                                     "wrong, or the camera moved past the volume's size)"]
        return prep, pose, list(notes)

    def estimate(self, frame: Frame, prep: Prepared, pose: np.ndarray | None, notes: list[str],
                 t: dict[str, float], t_start: float | None = None) -> FrameResult:
        """Ray cast, transfer, solve (and render) on the fused volume for an observed frame; ms into t,
        t["total"] measured from t_start (default: now). Between estimates (lighting.every) the latest one is
        held: no transfer or solve, the ray cast only where the render stage or the exposure gain needs it. With
        lighting.asynchronous every frame after the first holds the latest finished estimate, and a frame that finds
        the worker free (and lighting.every due) hands its estimate to it."""
        lc, rc = self.session.lighting, self.session.reconstruction
        t_all = time.perf_counter() if t_start is None else t_start
        F, diag, composite, region, in_view = None, None, None, None, None
        if pose is not None:
            self._frames += 1
            if self._in_flight is not None and self._in_flight[2].done():
                self._collect(t)
            # an estimate from no samples (a black frame, say) is not held over the good frames after it
            due = self._held is None or self._held_for + 1 >= lc.every or self._held[2].n_samples == 0
            beside = self._worker is not None and self._held is not None   # estimates run in the worker
            hold = not due or beside
            start = beside and due and self._in_flight is None
            full = not hold or start   # the maps at the lighting's stride
            maps = None
            if full or lc.exposure or self.render is not None:
                with self._timed(t, "raycast"):
                    grid = self.volume.dense_grid()
                    maps = raycast_surface(grid, self.intrinsics, pose, rc.depth_min, rc.depth_max,
                                           stride=lc.stride if full else self._held_stride(),
                                           normal_smoothing=rc.normal_smoothing_voxels)
            if hold:
                self._held_for += 1
                F, diag, gain = self._hold(prep, maps, pose, t)
                if start:
                    self._in_flight = (frame.index, self._frames, self._worker.submit(
                        self._estimate_beside, frame.index, prep, maps, pose, grid))
            else:
                F, diag, gain = self._estimate_lighting(frame.index, prep, maps, pose, grid, t)
                self._held, self._held_for = (frame.index, F, dataclasses.replace(diag, notes=list(diag.notes))), 0
            if self.render is not None:
                with self._timed(t, "render"):
                    composite = self.render(prep.linear, prep.depth, grid, maps, pose, F.sh, gain, diag.sun, t,
                                            frame.timestamp, frame.shutter)
                # the composite keeps the preprocessed colour outside the renderer's region: the frame's own unless
                # the luminance was denoised
                region = self.render.region if lc.denoise == "none" else None
                in_view = self.render.in_view
                notes = [*notes, *(f"render: {n}" for n in self.render.last.notes)]   # why it drew no shadow, say
        if F is None:  # no pose: keep the previous estimate, its light and the frame it came from (or darkness), weak
            prev = self.prev_F if self.prev_F is not None else np.zeros((3, self.solver_cfg.fit_bands ** 2))
            note = ("no pose: previous estimate repeated" if self.prev_F is not None else
                    "no pose and no earlier estimate: zero lighting")
            F, diag = Lighting(prev.copy()), SolveDiagnostics(notes=[note], estimated_frame=self.prev_from[0],
                                                              sun=self.prev_from[1])
        diag.notes = notes + list(diag.notes)
        if prep.uniform:
            diag.notes.append("the colour frame is one level everywhere (a camera's glitch?): no samples taken from it")
        if prep.saturated_fraction > 0.2:
            diag.notes.append(f"{prep.saturated_fraction:.0%} of pixels saturated")
        if prep.black_fraction > 0.5:
            diag.notes.append(f"{prep.black_fraction:.0%} of pixels black")
        if prep.valid_depth_fraction < 0.5:
            diag.notes.append(f"{1 - prep.valid_depth_fraction:.0%} of pixels without depth (0, NaN or outside "
                              "reconstruction.depth_min..depth_max)")
        if not diag.weak:
            self.prev_F, self.prev_from = F.sh.copy(), (diag.estimated_frame, copy.deepcopy(diag.sun))
        t["total"] = (time.perf_counter() - t_all) * 1000.0
        # the caller's own arrays: editing the result in place changed later frames' lighting (the held estimate, the
        # next solve's reference were the array handed back)
        return FrameResult(frame.index, frame.timestamp, Lighting(F.sh.copy()), diag, sh.dominant_direction(F.sh), t,
                           composite=composite, composite_region=region,
                           pose=None if pose is None else np.array(pose, dtype=np.float64), objects_in_view=in_view)
