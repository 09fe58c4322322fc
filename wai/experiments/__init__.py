"""``wai experiment NAME``: the one registry of experiments, and how each is run.

:data:`EXPERIMENTS` holds every experiment: its help (what it does, the files it writes, how
long it takes), which of the shared options apply to it, and its runner. The command line's
subcommands and help, and :func:`run_experiment`, read it. Each runner imports its experiment
when called, so building the command line imports none.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from wai.sweep import SweepOptions

Runner = Callable[[str | Path, Path, int | None, bool, "SweepOptions"], None]
"""Runs an experiment: ``(config, out, seeds, quick, sweep)`` (``seeds`` None where the
experiment has none)."""


def _run_validate(config: str | Path, out: Path, seeds: int | None, quick: bool,
                  sweep: SweepOptions) -> None:
    from wai.experiments.validate import print_validate, run_validate

    print_validate(run_validate(config, out, quick))


def _run_paper(config: str | Path, out: Path, seeds: int | None, quick: bool,
               sweep: SweepOptions) -> None:
    from wai.experiments.paper import run_paper

    run_paper(config, out, seeds, quick)


def _run_alterman(config: str | Path, out: Path, seeds: int | None, quick: bool,
                  sweep: SweepOptions) -> None:
    from wai.experiments.alterman import run_alterman

    run_alterman(config, out, seeds, quick)


def _run_tradeoffs(config: str | Path, out: Path, seeds: int | None, quick: bool,
                   sweep: SweepOptions) -> None:
    from wai.experiments.tradeoffs import run_tradeoffs

    run_tradeoffs(config, out, seeds, quick, sweep)


def _run_stability(config: str | Path, out: Path, seeds: int | None, quick: bool,
                   sweep: SweepOptions) -> None:
    from wai.experiments.stability import run_stability

    run_stability(config, out, seeds, quick, sweep)


def _run_budget(config: str | Path, out: Path, seeds: int | None, quick: bool,
                sweep: SweepOptions) -> None:
    from wai.experiments.budget import run_budget

    run_budget(config, out, seeds, quick, sweep)


def _run_calibration(config: str | Path, out: Path, seeds: int | None, quick: bool,
                     sweep: SweepOptions) -> None:
    from wai.experiments.calibration import run_calibration

    run_calibration(config, out, seeds, quick)


def _run_compare(config: str | Path, out: Path, seeds: int | None, quick: bool,
                 sweep: SweepOptions, methods: list[str] | None = None,
                 frames: int | None = None, first_seed: int = 0,
                 conditions: list[str] | None = None) -> None:
    from wai.experiments.compare import run_compare

    run_compare(config, out, seeds, quick, sweep, methods, frames, first_seed, conditions)


def _run_seawater(config: str | Path, out: Path, seeds: int | None, quick: bool,
                  sweep: SweepOptions) -> None:
    from wai.experiments.outputs import output_folder
    from wai.experiments.seawater import format_snr, seawater_snr
    from wai_core.io import write_json

    res = seawater_snr(config, seed=0, spp=4 if quick else None)
    write_json(output_folder(out) / "seawater_snr.json", res)
    print(format_snr(res))


@dataclass(frozen=True)
class Experiment:
    """One ``wai experiment NAME``: its help, its options and its runner.

    Attributes
    ----------
    summary : str
        One line, in ``wai experiment --help``.
    description : str
        ``wai experiment NAME --help``: what it does and what it writes (:func:`describe` adds
        :attr:`duration`).
    quick : str
        What ``--quick`` makes smaller.
    duration : str
        How long it takes on a 2-core machine, with and without ``--quick``.
    run : Runner
        Runs it (:func:`run_experiment` calls it).
    seeds : int or None
        The default of ``--seeds`` (seeds 0..K-1); None: the experiment has no ``--seeds``.
    quick_seeds : int or None
        The default of ``--seeds`` with ``--quick`` (an explicit ``--seeds`` wins).
    sweep : bool
        A sweep on the Dask runner (:mod:`wai.sweep`): the runner's options apply.
    methods : bool
        Takes ``--method SPEC`` (repeatable): methods of one's own added to those compared.
    frames : int or None
        The frames of each rendered sequence (the default of ``--frames``); None: the
        experiment renders no sequences and has no ``--frames``.
    quick_frames : int or None
        The default of ``--frames`` with ``--quick``.
    conditions : tuple of str
        The conditions ``--condition NAME`` may pick (repeatable; an experiment with them
        also takes ``--first-seed``); empty: it takes neither.
    """

    summary: str
    description: str
    quick: str
    duration: str
    run: Runner
    seeds: int | None = None
    quick_seeds: int | None = None
    sweep: bool = False
    methods: bool = False
    frames: int | None = None
    quick_frames: int | None = None
    conditions: tuple[str, ...] = ()


# Durations: --quick measured on an idle 2-core machine (CPU rendering, llvm_ad_rgb; the
# restoration's kernels already compiled); the full runs estimated from the quick ones by their
# number and size of frames.
EXPERIMENTS: dict[str, Experiment] = {
    "validate": Experiment(
        summary="the renderer against stock Mitsuba, the geometric model against the render",
        description=(
            "Renderer vs Mitsuba reference: the default renderer against renders made of "
            "Mitsuba's stock plugins and integrators only (ptracer + projector + dielectric, "
            "path + dielectric, independent sampler, high spp), flat water and U = 1: spot "
            "centroids in fixed windows, light in the spots and the image, the view's mean "
            "and RMS difference. Geometric model vs render: spot centres of the pattern render "
            "against the geometric model's chief rays, and the rendered view against the "
            "geometric view (flat water and waves at several wind speeds), then spot error and "
            "view noise against samples per pixel for both "
            "[render].sampling choices.\n\n"
            "Writes renderer_vs_mitsuba.csv, agreement.csv, spp_sweep.csv, view_spp_sweep.csv, "
            "spp_tradeoff.png and validate.json into --out, and prints the tables."
        ),
        quick="2 wave cases, spp 2/8/32 and 1/4, one run each, the reference at 64 / 16 spp",
        duration="about 40 s with --quick; roughly 20 min without (3 times the cases, spp "
                  "up to 64 and a 256-spp reference, 3 runs each)",
        run=_run_validate,
    ),
    "paper": Experiment(
        summary="the paper's figures and tables (Fig. 8-15, Table 2) from fresh runs",
        description=(
            "Renders, restores and scores the paper's configuration for each seed (the "
            "checkerboard and two natural images), Fig. 8's deflection curves, eq. 35's "
            "correspondence limit and a wave-amplitude sweep against it.\n\n"
            "Writes report.md, report.html (figures inline), paper.json, fig8_deflection.png, "
            "fig10_surface.png, fig11_features.png, fig11_surfaces.png, fig11f_profile.png, "
            "fig12_error_map.png, fig15_views.png, fig15d_corners.png, sweep_amplitude.png and "
            "one render folder per seed (seedNNN/, with restore/) into --out."
        ),
        quick="2 seeds, 3 amplitude factors",
        duration="about 15 s with --quick; roughly 2 min without (10 seeds, 8 amplitudes)",
        run=_run_paper,
        seeds=10,
        quick_seeds=2,
    ),
    "alterman": Experiment(
        summary="Alterman's sun sensor beside the structured light (Fig. 13-14, Table 2)",
        description=(
            "For each seed: the paper's system restored by the structured light (both "
            "anchors), then the sun sensor rendered through the same surface at each sun "
            "zenith angle and restored by Alterman's method, and one overcast frame.\n\n"
            "Writes report.md, results.csv (every number), fig13_error_maps.png, "
            "fig14_rmse_vs_sun.png and the render folders (seedNNN/) into --out."
        ),
        quick="seed 0 only, sun at 15 and 60 deg",
        duration="about 20 s with --quick; roughly 5 min without (3 seeds, 6 sun angles)",
        run=_run_alterman,
        seeds=3,
        quick_seeds=1,
    ),
    "tradeoffs": Experiment(
        summary="speed against accuracy of each choice (spacing, integrator, spp, warp step)",
        description=(
            "A sweep: frames rendered and restored for each pattern spacing, integrator, "
            "pattern spp, warp step and surface refinement, on every seed; each chart marks "
            "the default, with min-max bars over seeds.\n\n"
            "Writes tradeoffs.csv (one row per frame; a rerun skips the rows it holds), "
            "tradeoffs.parquet, tradeoffs.json (the run record), tradeoffs.png, tradeoffs.md "
            "and tradeoffs_series.json into --out, and prints the report."
        ),
        quick="3 spacings, 2 spp, 3 warp steps, one timed restoration per variant",
        duration="about 25 s with --quick; roughly 5 min without --quick (28 "
                  "frames, spp up to 32, 3 timed restorations per variant)",
        run=_run_tradeoffs,
        seeds=2,
        quick_seeds=2,
        sweep=True,
    ),
    "stability": Experiment(
        summary="where each method breaks (sea state, geometry, noise, blur, daylight, murk)",
        description=(
            "Sweeps over seeds: wind speed and wave height, pattern spacing, diffuser height, "
            "sensor signal, exposure time, daylight, turbidity, the sun sensor's sun angle, "
            "and the plain against the colour-coded pattern; each sweep's failure point "
            "against eq. 35's bound.\n\n"
            "Writes stability.csv (one row per frame; a rerun skips the rows it holds), "
            "stability.parquet, stability.json (the run record), stability.png, coded.png, "
            "confidence.png, stability.md and stability_summary.json into --out, and prints "
            "the report."
        ),
        quick="2-3 values per sweep, 2 sea states of the coded sweep",
        duration="about 2 min with --quick; roughly 25 min without (144 frames against 44)",
        run=_run_stability,
        seeds=2,
        quick_seeds=2,
        sweep=True,
    ),
    "budget": Experiment(
        summary="what each effect the geometric model leaves out costs (the error budget)",
        description=(
            "A sweep: every renderer-only effect (polarised projector light, sea water's "
            "index and dispersion, lens distortion and principal point, housing ports, the "
            "projector's defocus, a real diffuser, micro-roughness, capillary waves) rendered "
            "from zero through a realistic magnitude and beyond, each frame restored by the "
            "default restoration on the scene without it: surface RMSE (absolute and "
            "de-meaned), corner STD, status and consistency residual per effect and "
            "magnitude, the magnitude at which RMSE passes 0.05 and 1 mm, and whether the "
            "truth-free status flags the frames an effect ruins.\n\n"
            "Writes budget.csv (one row per frame; a rerun skips the rows it holds), "
            "budget.parquet, budget.json (the run record), budget.png, budget.md and "
            "budget_summary.json into --out, and prints the report."
        ),
        quick="one magnitude per effect (two for polarisation)",
        duration="about 30 s with --quick --seeds 1; roughly 45 min without (37 "
                  "magnitudes, 20 seeds: enough to say whether 95 % of frames restore ok)",
        run=_run_budget,
        seeds=20,
        quick_seeds=1,
        sweep=True,
    ),
    "calibration": Experiment(
        summary="what calibrating the cameras buys (real lenses: ideal, true, calibrated rig)",
        description=(
            "The cameras given real lenses (barrel distortion k1 = -0.2, k2 = 0.05 and the "
            "principal point 15, -10 px off the centre); their intrinsics calibrated from "
            "rendered checkerboards as 'wai calibrate' does; then, per seed, the paper's scene "
            "rendered with ideal and with real lenses, the real-lens frame restored with the "
            "ideal rig, the true rig, the checkerboards' rig and that rig with camera s "
            "refined on the flat-water pattern ('wai calibrate --flat'), each with the spots "
            "referred to the flat reference (the default) and as detected: surface RMSE, "
            "corner STD and status, against the ideal-lens frame restored with the ideal "
            "rig.\n\n"
            "Writes calibration.csv, calibration.json (with the calibrated intrinsics beside "
            "the truth), calibration.png, calibration.md and the render folders (seedNNN/) "
            "into --out."
        ),
        quick="one seed, 8 checkerboard views per camera",
        duration="about 25 s with --quick; roughly 12 min without (10 seeds, 20 renders)",
        run=_run_calibration,
        seeds=10,
        quick_seeds=1,
    ),
    "compare": Experiment(
        summary="every method on the same rendered sequences: structured light (alone and "
                "with the view's level), synthetic Schlieren, one's own, the image-only "
                "baselines",
        description=(
            "Each case (sea state, seed, condition) is one rendered sequence at 30 frames/s; "
            "every method restores it: the per-frame ones (structured light, structured light "
            "with its level from camera v's view, synthetic Schlieren at the gauge's level and "
            "at the structured light's, the unrestored view as a method of one's own, and any "
            "--method SPEC) "
            "frame by frame, the video ones (temporal mean, registration by optical flow, "
            "lucky-region fusion) from the whole sequence. The conditions: the paper's scene, "
            "its object a speckle (Schlieren's texture), the sensor's noise, and where the "
            "geometric method is weak (micro-roughness 0.01 and 0.02, gravity-capillary waves "
            "to 4, 5 and 6 omega_p, waves twice as steep, a defocused projector; through the "
            "speckle object). Scores against "
            "the truth: view SSIM and PSNR, corner STD, surface RMSE (and de-meaned) where a "
            "method has a surface; ms per frame and the frames each needs, charted speed "
            "against accuracy. Frames by condition: each per-frame method's ok frames under "
            "each condition, and how many lie within 0.05 mm of the same frame's RMSE without "
            "the condition's effect (the error budget's bar, frame by frame).\n\n"
            "Writes compare.csv (one row per case and method, with its frames' statuses and "
            "RMSEs; a rerun skips the rows it holds), compare.parquet, compare.json (the run "
            "record), compare_summary.json, "
            "compare.png, compare.md and the rendered sequences (cases/) into --out, and "
            "prints the report."
        ),
        quick="one sea state, one seed, the paper's scene and its speckle object, 8 frames",
        duration="about 3 min with --quick --seeds 1; roughly an hour and a half without (2 sea "
                 "states, 2 seeds, 10 conditions, 30 frames)",
        run=_run_compare,
        seeds=2,
        quick_seeds=1,
        sweep=True,
        methods=True,
        frames=30,
        quick_frames=8,
        conditions=("none", "speckle", "sensor", "rough_0.01", "rough_0.02", "capillary_4",
                    "capillary_5", "capillary_6", "steep_2", "defocus_2mm", "rough_0.01_256"),
    ),
    "seawater": Experiment(
        summary="spot SNR of a blue-green and a red pattern after the same sea water",
        description=(
            "The seed paper's blue-green argument in numbers: camera s's flat-water pattern "
            "in each colour, dimmed by 0, 1 and 5 m of sea water and read by one noisy "
            "sensor; the detected spots' SNR.\n\n"
            "Writes seawater_snr.json into --out and prints the table."
        ),
        quick="4 samples per pixel (the packaged paper scene's own count)",
        duration="about 5 s, with or without --quick on the paper scene (its own spp is 4)",
        run=_run_seawater,
    ),
}
"""The experiments of ``wai experiment``, by name."""


def describe(name: str, width: int = 79) -> str:
    """The ``--help`` description of experiment ``name``, with its duration, its paragraphs
    wrapped to ``width`` columns."""
    import textwrap

    exp = EXPERIMENTS[name]
    text = f"{exp.description}\n\nTakes (2 cores): {exp.duration}."
    return "\n\n".join(textwrap.fill(par, width) for par in text.split("\n\n"))


def run_experiment(name: str, config: str | Path = "paper", out: str | Path | None = None,
                   seeds: int | None = None, quick: bool = False,
                   sweep: SweepOptions | None = None, methods: list[str] | None = None,
                   frames: int | None = None, first_seed: int | None = None,
                   conditions: list[str] | None = None) -> None:
    """Run experiment ``name`` into ``out`` and print its tables.

    Parameters
    ----------
    name : str
        A key of :data:`EXPERIMENTS`.
    config : str or Path
        The scene: a packaged name or a TOML file.
    out : str, Path or None
        The output folder; None: ``renders/<name>``.
    seeds : int or None
        Seeds 0..seeds-1, for the experiments that have seeds; None: its
        :attr:`Experiment.seeds`, or :attr:`Experiment.quick_seeds` with ``quick``.
    quick : bool
        The small version (:attr:`Experiment.quick`).
    sweep : SweepOptions or None
        Where and how a sweep's points run; None: the defaults of :class:`SweepOptions`.
    methods : list of str or None
        Methods of one's own (``module:Class``, a file, an entry point) for the experiments
        that compare methods (:attr:`Experiment.methods`).
    frames : int or None
        Frames of each rendered sequence, for the experiments that render sequences
        (:attr:`Experiment.frames`); None: its :attr:`Experiment.frames`, or
        :attr:`Experiment.quick_frames` with ``quick``.
    first_seed : int or None
        The first seed (seeds ``first_seed`` .. ``first_seed + seeds - 1``), for the
        experiments with conditions (:attr:`Experiment.conditions`); None: 0.
    conditions : list of str or None
        Only these of :attr:`Experiment.conditions`; None: the experiment's own choice.

    Raises
    ------
    WaiInputError
        ``name`` is no experiment, or an option it does not take.
    """
    from wai.sweep import SweepOptions
    from wai_core.errors import WaiInputError

    if name not in EXPERIMENTS:
        raise WaiInputError(f"no experiment {name!r}: one of {', '.join(EXPERIMENTS)}")
    exp = EXPERIMENTS[name]
    out = Path("renders") / name if out is None else Path(out)
    if seeds is None:
        seeds = exp.quick_seeds if quick else exp.seeds
    args = (config, out, seeds, quick,
            SweepOptions() if sweep is None else sweep)
    if methods and not exp.methods:
        raise WaiInputError(f"experiment {name}: takes no --method")
    if frames is not None and exp.frames is None:
        raise WaiInputError(f"experiment {name}: takes no --frames")
    if (first_seed is not None or conditions) and not exp.conditions:
        raise WaiInputError(f"experiment {name}: takes no --first-seed or --condition")
    extra: dict[str, object] = {}
    if exp.conditions:
        extra.update(first_seed=first_seed or 0, conditions=list(conditions or []))
    if exp.methods:
        extra["methods"] = list(methods or [])
    if exp.frames is not None:
        extra["frames"] = frames if frames is not None else (
            exp.quick_frames if quick else exp.frames)
    exp.run(*args, **extra)
    if out.is_dir():  # the folder's page, with every figure and table the run left there
        from wai_core.report import write_report

        write_report(out, title=f"{out.name}: wai experiment {name}")
