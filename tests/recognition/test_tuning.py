"""Every tuned value of the core is a documented ``*Params`` field that says where it was chosen, with one
spelling of "off" and of "auto"; ``docs/tuning.md`` is generated from those fields and cannot drift."""

from __future__ import annotations

import ast
import dataclasses
import importlib
import pkgutil
from pathlib import Path

import pytest

import recognition
from harness.tuning import DOC_PATH, table
from recognition.change import ChangeParams
from recognition.classification import SelectParams
from recognition.describe import DescribeParams
from recognition.localisation import MatchParams
from recognition.peers.primitives import PrimitiveParams
from recognition.peers.registration import RegistrationParams
from recognition.segmentation import SegmentationParams
from recognition.tuning import CONSTANTS, PARAMS_MODULES, params_classes, tuned

ROOT = Path(recognition.__file__).resolve().parent


def _modules() -> list[str]:
    return sorted(m.name for m in pkgutil.walk_packages([str(ROOT)], "recognition."))


def test_docs_tuning_is_generated_from_the_code():
    assert DOC_PATH.read_text() == table(), "docs/tuning.md is stale: run `python -m harness.tuning --write`"


def _only_holds_params(cls: type) -> bool:
    """A container of other ``*Params`` (``CoreParams``): no value of its own to tune."""
    return all(f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(f.default_factory())
               for f in dataclasses.fields(cls))


def test_every_params_dataclass_of_the_core_is_in_the_table():
    found = set()
    for name in _modules():
        module = importlib.import_module(name)
        for obj in vars(module).values():
            if (isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__name__.endswith("Params")
                    and obj.__module__ == name and not _only_holds_params(obj)):
                found.add(obj)
    listed = set(params_classes())
    assert found == listed, f"add the module of {sorted(c.__name__ for c in found - listed)} to PARAMS_MODULES"
    assert len(PARAMS_MODULES) == len({c.__module__ for c in listed})


@pytest.mark.parametrize("cls", params_classes(), ids=lambda c: c.__name__)
def test_every_field_says_its_unit_and_where_it_was_chosen(cls):
    for f in dataclasses.fields(cls):
        assert f.metadata.get("unit") and f.metadata.get("chosen"), f"{cls.__name__}.{f.name}: declare it with tuned()"


def _numeric(node: ast.AST) -> bool:
    """A number, or an expression of numbers only (``-3``, ``np.cos(np.radians(30.0))``, ``2 * 4``)."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, int | float) and not isinstance(node.value, bool)
    if isinstance(node, ast.UnaryOp):
        return _numeric(node.operand)
    if isinstance(node, ast.BinOp):
        return _numeric(node.left) and _numeric(node.right)
    if isinstance(node, ast.Call):  # a scalar function of numbers: float(np.deg2rad(12.0)), math.cos(...)
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) else getattr(f, "id", "")
        return name in _SCALAR_FUNCTIONS and bool(node.args) and all(_numeric(a) for a in node.args)
    return False


_SCALAR_FUNCTIONS = {"float", "int", "radians", "deg2rad", "degrees", "cos", "sin", "tan", "sqrt", "exp", "log"}


def test_no_numeric_module_constant_but_the_named_exceptions():
    """A tuned value lives in a ``*Params`` field; the few named numeric constants left are listed, with why, in
    ``recognition.tuning.CONSTANTS`` (and docs/tuning.md)."""
    allowed = {(m, n) for m, n, _, _ in CONSTANTS}
    found = set()
    for path in ROOT.rglob("*.py"):
        module = "recognition." + ".".join(path.relative_to(ROOT).with_suffix("").parts)
        module = module.removesuffix(".__init__")
        for node in ast.parse(path.read_text()).body:
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] \
                if isinstance(node, ast.AnnAssign) and node.value is not None else []
            for t in targets:
                if isinstance(t, ast.Name) and t.id.lstrip("_").isupper() and _numeric(node.value):
                    found.add((module, t.id))
    assert found == allowed, f"unlisted: {sorted(found - allowed)}; listed but gone: {sorted(allowed - found)}"


@pytest.mark.parametrize("cls, field, value", [
    (SegmentationParams, "crease_baseline", 0), (SegmentationParams, "class_min_pixels", 0),
    (SegmentationParams, "seed_erosion", None), (SegmentationParams, "decimation", None),
    (SegmentationParams, "split_seeds", None), (SelectParams, "cone_score_skip", 0.0),
    (SelectParams, "outlier_k", 0.0), (SelectParams, "min_inliers", 1.0), (SelectParams, "plane_gate", 0.0),
    (MatchParams, "length_m", 0.0), (RegistrationParams, "voxel_size", None),
    (RegistrationParams, "icp_voxel_size", None), (PrimitiveParams, "epsilon", None),
    (PrimitiveParams, "cluster_epsilon", None)])
def test_the_old_spellings_of_off_and_auto_are_refused(cls, field, value):
    """Off is None and derived is "auto": the numbers and Nones that used to stand for them now fail loudly, in
    one line naming the field, instead of meaning something else."""
    with pytest.raises(ValueError, match=field):
        cls(**{field: value})


@pytest.mark.parametrize("cls, field", [
    (SegmentationParams, "crease_baseline"), (SegmentationParams, "class_min_pixels"),
    (SegmentationParams, "max_tiled_leftover"), (SegmentationParams, "axis_split_pixels"),
    (SelectParams, "cone_score_skip"), (SelectParams, "outlier_k"), (SelectParams, "min_inliers"),
    (SelectParams, "plane_gate"), (SelectParams, "huber")])
def test_none_turns_a_limit_or_a_step_off(cls, field):
    assert getattr(cls(**{field: None}), field) is None


@pytest.mark.parametrize("cls, field, value", [
    (MatchParams, "same_pose_angle_deg", 0.0), (MatchParams, "same_pose_rel", -0.02),
    (MatchParams, "width_directions", 0), (MatchParams, "width_points", 2), (ChangeParams, "overlap_share", 0.0),
    (ChangeParams, "revealed_share", 1.5), (ChangeParams, "new_gap_px", -1), (DescribeParams, "merge_min_contacts", 0),
    (SelectParams, "single_sheet_fraction", 0.2), (SelectParams, "merge_points", 5), (SelectParams, "refit_trim", 0.0),
    (SelectParams, "refit_iter", 0), (SelectParams, "refit_final_points", 5), (SelectParams, "criterion", "mdl")])
def test_the_moved_values_are_validated_like_the_others(cls, field, value):
    with pytest.raises(ValueError, match=field):
        cls(**{field: value})


def test_tuned_needs_a_unit_and_where_the_value_was_chosen():
    with pytest.raises(ValueError, match="unit"):
        tuned(1.0, unit="", chosen="x")
    with pytest.raises(ValueError, match="chosen"):
        tuned(1.0, unit="m", chosen="")
    with pytest.raises(TypeError, match="exactly one"):
        tuned(unit="m", chosen="x")
