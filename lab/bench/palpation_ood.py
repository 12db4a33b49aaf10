"""Out-of-distribution palpation benchmark: phantom families that vary one factor at a time.

``teletouch bench palpation --ood`` builds, per family, ``--runs`` phantoms (seeds
``first-seed .. first-seed + runs - 1``), simulates one palpation session on each
(:func:`lab.bench.palpation_session.simulate_session`: the station's own pipeline in simulated
time, the realistic world unless ``--ideal``), analyses the recording with the local station's
analysis (:func:`local_site.palpation.analyse_recording`, what the operator received only) and
scores it against the phantom's ground truth in PHANTOM coordinates (so a registration error
that nothing corrects shows up as localization error).

Families (the others at the base: one benign inclusion, radius 5 mm, 7 mm deep, 6x contrast,
raster operator over the whole workspace, realistic world):

=============  ====================================================================
size           radius 2.5 .. 8 mm
depth          centre depth 4 .. 14 mm
contrast       inclusion / background modulus 1.5 .. 50x (log spaced)
type           two inclusions, one benign (contrast 2.5-5x, sharp boundary 0.05-0.3 mm) and
               one malignant (8-16x, graded boundary 0.8-2 mm); each round or lobulated
               at random, INDEPENDENT of its type; malignant ranks more severe
count          0, 1, 2, 3, 4 inclusions ranked by size and stiffness together
free-operator  the type phantoms, palpated by a free-moving operator (random strokes)
coverage       the type phantoms, a raster over 40 .. 100 % of the workspace area
registration   the type phantoms, registration error 0 .. 4 mm and 0 .. 6 degrees
noise          the type phantoms, sensing noise (camera, LED drift, force, position) 0 .. 3x
               the realistic level, registration error zero
frame-rate     the type phantoms, tactile frames at 4 .. 60 Hz (log spaced; the others
               at 20 Hz): how many frames reach the analysis, as on a loaded machine
=============  ====================================================================

Recordings are cached (``--cache DIR``) by family, index, seed and world so the analysis can
be re-scored without simulating again; the key holds nothing of the analysis settings, which
are applied afresh on every re-analysis (``--map-config`` / ``--detection-config`` override
them, :func:`configured_analysis`).
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from lab.bench.palpation_session import Operator, simulate_registration, simulate_session
from lab.scoring import score_findings
from local_site.palpation import DetectionConfig, MapConfig, analyse_recording
from local_site.recording import Recording
from remote_site.agent.world import IDEAL, REALISTIC, Realism, Registration, world_for
from remote_site.phantom.phantom_file import phantom_from_dict
from remote_site.registration import RegistrationEstimate
from shared.errors import CalibrationError, ConfigError, InputDataError
from shared.workspace import WorkspaceMap

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

__all__ = ["FAMILIES", "Case", "config_overrides", "configured_analysis", "make_case", "run_case",
           "summarise_ood"]

LAYER = {"size_mm": [100.0, 100.0], "thickness_mm": 20.0, "modulus_kpa": 50.0}
E_BG = 50.0
#: the workspace reaches +-29 mm of the phantom centre; inclusions stay inside +-22 mm
PLACE = {"half_mm": 22.0, "min_separation_mm": 18.0}
#: the phantom's registration markers (design positions), as in the shipped scenes
FIDUCIALS = [{"center_mm": [x, y]} for x, y in ((-42.0, 0.0), (0.0, -42.0), (42.0, 0.0),
                                                 (0.0, 42.0))]
#: the issue's detection target: radius >= 3 mm, depth <= 12 mm, contrast >= 2x
TARGET = {"radius_mm": 3.0, "depth_mm": 12.0, "contrast": 2.0}
#: tactile frames per simulated second of every family but ``frame-rate``
FRAME_RATE_HZ = 20.0


@dataclass(frozen=True)
class Case:
    """One phantom and session of a family."""

    family: str
    index: int
    seed: int
    factor: float
    phantom: dict[str, Any]
    operator: Operator
    realism: Realism
    registration: Registration | None = None
    frame_rate_hz: float = FRAME_RATE_HZ

    @property
    def key(self) -> str:
        world = "ideal" if self.realism == IDEAL else f"r{hash(self.realism) & 0xFFFFFF:06x}"
        rate = "" if self.frame_rate_hz == FRAME_RATE_HZ else f"-{self.frame_rate_hz:.3g}hz"
        # the phantom itself is in the key: a family's varied value depends on how many
        # phantoms it has (``--runs``), and another --runs must not reuse these sessions
        phantom = hashlib.sha256(json.dumps(self.phantom, sort_keys=True, default=str)
                                 .encode()).hexdigest()[:8]
        return f"{self.family}-{self.index:02d}-s{self.seed}-{world}{rate}-p{phantom}"


def _inclusion(rng: np.random.Generator, kind: str, radius: float, depth: float) -> dict[str, Any]:
    if kind == "benign":
        contrast, boundary = rng.uniform(2.5, 5.0), rng.uniform(0.05, 0.3)
    else:
        contrast, boundary = rng.uniform(8.0, 16.0), rng.uniform(0.8, 2.0)
    inc: dict[str, Any] = {"kind": kind, "depth_mm": depth, "radius_mm": radius,
                           "modulus_kpa": float(E_BG * contrast),
                           "boundary_width_mm": float(boundary),
                           "severity_rank": 1 if kind == "benign" else 2}
    if rng.random() < 0.5:  # lobulated, whatever the type
        inc["outline"] = {"orders": [3, 5, 7], "amplitude": [0.05, 0.1]}
        inc["surface_roughness"] = 0.15
    return inc


def _typed_pair(rng: np.random.Generator) -> list[dict[str, Any]]:
    return [_inclusion(rng, kind, float(rng.uniform(4.0, 7.0)), 7.0)
            for kind in ("benign", "malignant")]


def _base(**over: Any) -> dict[str, Any]:
    return {"kind": "benign", "depth_mm": 7.0, "radius_mm": 5.0, "modulus_kpa": 6.0 * E_BG,
            "boundary_width_mm": 0.05, **over}


def _lin(i: int, n: int, lo: float, hi: float) -> float:
    return lo + (hi - lo) * (i / (n - 1) if n > 1 else 0.5)


def _geom(i: int, n: int, lo: float, hi: float) -> float:
    return float(math.exp(_lin(i, n, math.log(lo), math.log(hi))))


def _coverage_region(rng: np.random.Generator,
                     fraction: float) -> tuple[float, float, float, float]:
    side = 58.0 * math.sqrt(fraction)
    x0 = float(rng.uniform(1.0, 59.0 - side))
    y0 = float(rng.uniform(1.0, 59.0 - side))
    return (x0, x0 + side, y0, y0 + side)


def make_case(family: str, index: int, n: int, seed: int, ideal: bool = False) -> Case:
    """The ``index``-th of ``n`` cases of ``family`` (deterministic in ``seed``)."""
    rng = np.random.default_rng([seed, index, 0x00D])
    realism = IDEAL if ideal else REALISTIC
    operator = Operator(seed=seed)
    registration: Registration | None = None
    frame_rate_hz = FRAME_RATE_HZ
    factor = float(index)
    if family == "size":
        factor = _lin(index, n, 2.5, 8.0)
        incs = [_base(radius_mm=factor)]
    elif family == "depth":
        factor = _lin(index, n, 4.0, 14.0)
        incs = [_base(depth_mm=factor)]
    elif family == "contrast":
        factor = _geom(index, n, 1.5, 50.0)
        incs = [_base(modulus_kpa=factor * E_BG)]
    elif family == "count":
        factor = float(index % 5)
        incs = [_base(radius_mm=3.5 + 0.9 * k, modulus_kpa=E_BG * 3.0 * 1.7 ** k,
                      severity_rank=k + 1) for k in range(int(factor))]
    elif family in ("type", "free-operator", "coverage", "registration", "noise",
                    "frame-rate"):
        incs = _typed_pair(rng)
        if family == "frame-rate":
            factor = frame_rate_hz = _geom(index, n, 4.0, 60.0)
        elif family == "free-operator":
            operator = Operator(kind="free", seed=seed)
        elif family == "coverage":
            factor = _lin(index, n, 0.4, 1.0)
            operator = Operator(region=_coverage_region(rng, factor), seed=seed)
        elif family == "registration":
            factor = _lin(index, n, 0.0, 4.0)
            angle = rng.uniform(0, 2 * math.pi)
            registration = Registration(factor * math.cos(angle), factor * math.sin(angle), 0.0,
                                        float(rng.choice([-1, 1])) * 1.5 * factor)
        elif family == "noise":
            factor = _lin(index, n, 0.0, 3.0)
            realism = replace(REALISTIC.scaled(factor), registration_mm=0.0,
                              registration_deg=0.0, registration_z_mm=0.0,
                              tissue_nonlinearity=REALISTIC.tissue_nonlinearity)
            registration = Registration()
    else:
        raise KeyError(family)
    phantom = {"name": f"ood-{family}-{index}", "layer": LAYER, "placement": PLACE,
               "inclusion": [{"id": f"T{k + 1}", **inc} for k, inc in enumerate(incs)],
               "fiducial": FIDUCIALS}
    return Case(family, index, seed, factor, phantom, operator, realism, registration,
                frame_rate_hz)


FAMILIES: tuple[str, ...] = ("size", "depth", "contrast", "type", "count", "free-operator",
                             "coverage", "registration", "noise", "frame-rate")


def _save(rec: Recording, path: Path) -> None:
    arrays = {k: getattr(rec, k) for k in (
        "platform_t_us", "platform_mm", "frame_center_mm", "frame_pitch_mm", "frame_contact",
        "frame_force_n", "frame_indentation_mm", "frame_height_mm", "frame_rx_us", "frame_seq")}
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, meta_json=np.asarray(json.dumps(rec.meta, default=str)), **arrays)
    tmp.replace(path)


def _load(path: Path) -> Recording:
    with np.load(path, allow_pickle=False) as data:
        fields = {k: data[k] for k in data.files if k != "meta_json"}
        meta = json.loads(str(data["meta_json"]))
    return Recording(meta=meta, **fields)


Analyse = Callable[[Recording, dict[str, Any]], list[Any]]


def default_analysis(rec: Recording, context: dict[str, Any]) -> list[Any]:
    """The local station's analysis, in the workspace map the recording says it used,
    corrected by the session's fiducial registration when one was made."""
    return configured_analysis()(rec, context)


def configured_analysis(map_config: MapConfig | None = None,
                        detection: DetectionConfig | None = None) -> Analyse:
    """:func:`default_analysis` with other map and detection settings (the recordings do
    not depend on them, so cached sessions can be re-analysed with any)."""
    def analyse(rec: Recording, context: dict[str, Any]) -> list[Any]:
        est = context.get("registration")
        if est is None:
            return analyse_recording(rec, map_config=map_config, detection=detection)
        # platform -> arm (the recorded map) -> phantom (the estimated rigid motion)
        return analyse_recording(rec, WorkspaceMap().registered(est.dx_mm, est.dy_mm,
                                                                est.yaw_deg),
                                 map_config, detection)
    return analyse


_T = TypeVar("_T", bound="DataclassInstance")


def config_overrides(cls: type[_T], text: str) -> _T:
    """``cls()`` with ``name=value,...`` overrides (numbers and booleans; for the
    ``--map-config`` / ``--detection-config`` flags).

    Raises:
        ConfigError: an unknown field or a malformed item.
    """
    types = {f.name: str(f.type) for f in fields(cls)}
    values: dict[str, Any] = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep or name not in types:
            raise ConfigError(f"{cls.__name__}: expected name=value with a known field, "
                              f"got {item!r}; fields: {sorted(types)}")
        kind = types[name]
        if kind == "bool":
            flag = {"1": True, "true": True, "yes": True, "0": False, "false": False,
                    "no": False}.get(value.strip().lower())
            if flag is None:
                raise ConfigError(f"{cls.__name__}.{name}: not a boolean: {value!r}")
            values[name] = flag
            continue
        if "None" in kind and value.strip().lower() == "none":
            values[name] = None
            continue
        try:
            values[name] = int(value) if kind == "int" else float(value)
        except ValueError as err:
            raise ConfigError(f"{cls.__name__}.{name}: not a number: {value!r}") from err
    return cls(**values)


def _registration(world: Any, path: Path | None) -> RegistrationEstimate:
    if path is not None and path.exists():
        data: dict[str, Any] = json.loads(path.read_text())
        data["measured_arm_mm"] = tuple(tuple(p) for p in data["measured_arm_mm"])
        return RegistrationEstimate(**data)
    est = simulate_registration(world)
    if path is not None:
        path.write_text(json.dumps(est.to_dict()))
    return est


def run_case(case: Case, cache: Path | None = None, analyse: Analyse = default_analysis,
             register: bool = True) -> dict[str, Any]:
    """Simulate (or load) the case's session, analyse and score it.

    With ``register`` the fiducial registration is simulated too and the analysis maps the
    recording through it. (The live station puts the registration into its workspace map
    before palpation, so the operator's strokes land where meant; here the session is
    recorded through the designed map and corrected afterwards, which shifts the palpated
    area by the registration error but scores the same positions.)"""
    phantom = phantom_from_dict(case.phantom, case.seed, source=case.key)
    world = world_for(phantom, case.realism, case.seed, case.registration)
    path = cache / f"{case.key}.npz" if cache is not None else None
    t0 = time.monotonic()
    if path is not None and path.exists():
        rec = _load(path)
    else:
        rec = simulate_session(world, case.operator, workspace=WorkspaceMap(),
                               frame_rate_hz=case.frame_rate_hz)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            _save(rec, path)
    t1 = time.monotonic()
    truth = world.phantom.ground_truth()
    est = None
    registration_error = None
    if register:
        try:
            est = _registration(world, path.with_suffix(".reg.json") if path is not None
                                else None)
        except CalibrationError as err:  # scored without registration, and said so
            registration_error = str(err)
    try:
        findings = analyse(rec, {"world": world, "case": case, "registration": est})
    except InputDataError as err:
        return {"family": case.family, "index": case.index, "seed": case.seed,
                "factor": case.factor, "error": str(err)}
    score = score_findings(findings, truth)
    inclusions = []
    matched = {m["id"]: m for m in score["matches"]}
    for t in truth["tumors"]:
        m = matched.get(t["id"])
        contrast = t["modulus_kpa"] / phantom.layer.modulus_kpa
        inclusions.append({
            "id": t["id"], "kind": t["kind"], "radius_mm": t["radius_mm"],
            "depth_mm": t["depth_mm"], "contrast": contrast,
            "lobulated": bool(t["harmonics"]),
            "target": (t["radius_mm"] >= TARGET["radius_mm"]
                       and t["depth_mm"] <= TARGET["depth_mm"]
                       and contrast >= TARGET["contrast"]),
            "found": m is not None, "error_mm": m["error_mm"] if m else None,
            "found_kind": m["found_kind"] if m else None})
    return {"family": case.family, "index": case.index, "seed": case.seed,
            "factor": case.factor, "frames": rec.frames,
            "registration": world.registration.to_dict(),
            "registration_estimate": est.to_dict() if est is not None else None,
            "registration_error": registration_error,
            "inclusions": inclusions, "false_positives": score["false_positives"],
            "kendall_tau": score["kendall_tau"],
            "findings": [f.to_dict() for f in findings],
            "simulate_s": t1 - t0, "analyse_s": time.monotonic() - t1}


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def summarise_ood(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per family plus an ``all`` row."""
    rows = []
    families = sorted({r["family"] for r in runs}, key=lambda f: (
        FAMILIES.index(f) if f in FAMILIES else 99, f))
    for family in [*families, "all"]:
        rs = [r for r in runs if family in ("all", r["family"])]
        ok = [r for r in rs if "error" not in r]
        incs = [i for r in ok for i in r["inclusions"]]
        target = [i for i in incs if i["target"]]
        found = [i for i in incs if i["found"]]
        errors = [i["error_mm"] for i in found]
        conf = {f"{t[0]}->{f[0]}": sum(1 for i in found if i["kind"] == t
                                      and i["found_kind"] == f)
                for t in ("benign", "malignant") for f in ("benign", "malignant")}
        typed = sum(conf.values())
        uncertain = sum(1 for i in found if i["found_kind"] == "uncertain")
        taus = [r["kendall_tau"] for r in ok if r["kendall_tau"] is not None]
        rows.append({
            "family": family, "phantoms": len(rs), "failed": len(rs) - len(ok),
            "inclusions": len(incs),
            "detection": len(found) / len(incs) if incs else None,
            "detection_target": (sum(i["found"] for i in target) / len(target)
                                 if target else None),
            "fp_per_phantom": (sum(r["false_positives"] for r in ok) / len(ok)) if ok else None,
            "type_accuracy": ((conf["b->b"] + conf["m->m"]) / (typed + uncertain)
                              if typed + uncertain else None),
            "confusion b->b b->m m->b m->m": " ".join(str(conf[k]) for k in
                                                    ("b->b", "b->m", "m->b", "m->m")),
            "uncertain": uncertain,
            "loc_mean_mm": float(np.mean(errors)) if errors else None,
            "loc_p95_mm": _pct(errors, 95),
            "tau_mean": float(np.mean(taus)) if taus else None,
            "tau_n": len(taus),
        })
    return rows


def failures(runs: list[dict[str, Any]], limit: int = 40) -> list[str]:
    """Plain lines naming every missed inclusion, false positive and mistyped inclusion."""
    out = []
    for r in runs:
        tag = f"{r['family']} #{r['index']} (seed {r['seed']}, factor {r['factor']:.3g})"
        if "error" in r:
            out.append(f"{tag}: analysis failed: {r['error']}")
            continue
        for i in r["inclusions"]:
            desc = (f"{i['kind']} r {i['radius_mm']:.1f} mm, depth {i['depth_mm']:.1f} mm, "
                    f"{i['contrast']:.1f}x, {'lobulated' if i['lobulated'] else 'round'}")
            if not i["found"]:
                out.append(f"{tag}: MISSED {desc}")
            elif i["found_kind"] != i["kind"]:
                out.append(f"{tag}: typed {i['found_kind']}: {desc}")
        if r["false_positives"]:
            out.append(f"{tag}: {r['false_positives']} false positive(s)")
    return out[:limit] + ([f"... and {len(out) - limit} more"] if len(out) > limit else [])


def plot_ood(runs: list[dict[str, Any]], path: Path) -> None:
    """Detection and localization against the varied factor, one panel per family."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    families = [f for f in FAMILIES if any(r["family"] == f for r in runs)]
    cols = 3
    rows = math.ceil(len(families) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(12, 3.2 * rows), squeeze=False)
    for ax, family in zip(axes.flat, families, strict=False):
        rs = [r for r in runs if r["family"] == family and "error" not in r]
        x = [r["factor"] for r in rs]
        det = [np.mean([i["found"] for i in r["inclusions"]]) if r["inclusions"] else np.nan
               for r in rs]
        err = [np.mean([i["error_mm"] for i in r["inclusions"] if i["found"]])
               if any(i["found"] for i in r["inclusions"]) else np.nan for r in rs]
        fp = [r["false_positives"] for r in rs]
        ax.plot(x, det, "o", label="detected share")
        ax.plot(x, fp, "rx", label="false positives")
        ax2 = ax.twinx()
        ax2.plot(x, err, "k^", ms=4, label="loc. error (mm)")
        ax2.set_ylabel("mm", fontsize=7)
        ax.set_title(family, fontsize=9)
        ax.set_ylim(-0.1, max(2.1, max(fp, default=0) + 0.1))
    for ax in list(axes.flat)[len(families):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
