"""``harness scene``: generate, perturb and export scene models."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from scenes.families import FAMILIES, family_member
from scenes.generator import GeneratorConfig, generate_factory, mockup_model
from scenes.mjcf import export_mjcf
from scenes.model import SceneModel
from scenes.perturb import PerturbationSpec, perturb

NAME = "scene"
HELP = "generate, perturb and export scene models"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="scene_command", metavar="ACTION", required=True)
    g = sub.add_parser("generate", help="generate a factory bay (or the mock-up) as a scene YAML")
    g.add_argument("--seed", type=int, default=0, help="generator seed (default 0)")
    g.add_argument("--config", type=Path, help="generator config YAML (default: built-in factory bay)")
    g.add_argument("--mockup", action="store_true", help="write the paper-like 1:10 mock-up instead")
    g.add_argument("--family", choices=tuple(FAMILIES),
                   help="write member --seed of a scene family, as a suite's `family:` group makes it (with "
                        "--config: that family config; default: the family's shipped one)")
    g.add_argument("--name", help="scene name (default from the seed)")
    g.add_argument("--out", type=Path, required=True, help="output scene YAML")
    p = sub.add_parser("perturb", help="draw the actual scene and its change truth from an a priori model")
    p.add_argument("model", type=Path, help="a priori scene YAML")
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--spec", type=Path, help="perturbation spec YAML (default: built-in factory magnitudes)")
    p.add_argument("--out", type=Path, required=True, help="output directory (actual.yaml, truth.json)")
    m = sub.add_parser("mjcf", help="export a scene YAML to MuJoCo MJCF")
    m.add_argument("model", type=Path, help="scene YAML")
    m.add_argument("--out", type=Path, required=True, help="output .xml")
    m.add_argument("--mesh-tolerance", type=float, default=1e-4,
                   help="mesh surface error per metre of feature size (default 1e-4)")


def run(args: argparse.Namespace) -> int:
    return {"generate": _generate, "perturb": _perturb, "mjcf": _mjcf}[args.scene_command](args)


def _generate(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    if args.mockup and args.family:
        raise ValueError("--mockup writes the one fixed mock-up; --family mockup draws a member of the family")
    if args.mockup:
        model = mockup_model()
    elif args.family:
        model = family_member(args.family, args.seed, args.config)
        if args.name:
            model = SceneModel(args.name, model.objects)
    else:
        cfg = GeneratorConfig.load(args.config) if args.config else GeneratorConfig()
        model = generate_factory(cfg, args.seed, args.name)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    model.save(args.out)
    print(f"{args.out}: {len(model.objects)} objects, {len(model.features)} features "
          f"({time.perf_counter() - t0:.2f} s)")
    return 0


def _perturb(args: argparse.Namespace) -> int:
    model = SceneModel.load(args.model)
    spec = PerturbationSpec.load(args.spec) if args.spec else PerturbationSpec()
    actual, truth = perturb(model, spec, args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    actual.save(args.out / "actual.yaml")
    (args.out / "truth.json").write_text(truth.to_json(), encoding="utf-8")
    counts: dict[str, int] = {}
    for c in truth.objects.values():
        counts[c.label] = counts.get(c.label, 0) + 1
    counts["new"] = len(truth.new_objects)
    print(f"{args.out}: objects {json.dumps(counts)}")
    for note in truth.notes:
        print(f"  note: {note}")
    return 0


def _mjcf(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    model = SceneModel.load(args.model)
    exported = export_mjcf(model, args.mesh_tolerance)
    exported.load_model()  # fail here, not in the viewer, if MuJoCo rejects it
    args.out.parent.mkdir(parents=True, exist_ok=True)
    exported.save(args.out)
    print(f"{args.out}: {len(exported.geom_names)} geoms, {len(exported.surfaces)} surfaces "
          f"({time.perf_counter() - t0:.2f} s); view with: python -m mujoco.viewer --mjcf {args.out}")
    return 0
