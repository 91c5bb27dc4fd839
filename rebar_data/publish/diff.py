"""``rebar dataset diff OLD NEW``: what changed between two versions of a dataset, and the bump it needs.

Works on built datasets and on published bundles alike (both hold ``meta/info.json`` and ``tables/``).
It compares the resolved configs key by key, the schema (schema version and table columns), the counts
per split, which images kept their split, and the distributions a user of the data cares about:
keypoints per image, visibility, and the coverage of lighting, material, surroundings and sensor
parameters (two-sample Kolmogorov-Smirnov for numbers, total variation distance for categories).

Version rule (semantic versioning, read for data):
- major: a consumer's code, labels or benchmark numbers stop being comparable: schema major version,
  a table column removed or retyped, label meaning (label rules, OKS sigma, keypoint names, conventions,
  camera intrinsics), split rule or fractions, or evaluation images (val, test) removed or moved;
- minor: new or different content under the same contract: images added, config changes to the mesh,
  scene, camera paths, rendering or seed, labels that changed with the same config, columns added;
- patch: the same content, fixed: only metadata (description, generator version) or image bytes changed
  with identical labels and config;
- none: nothing changed.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from rebar_data.config import ConfigError
from rebar_data.dataset import layout
from rebar_data.dataset.layout import DatasetFormatError, DatasetInfo

LEVELS = ("none", "patch", "minor", "major")
KS_P_SHIFT = 0.01  # a numeric distribution shifted when the KS test rejects equality at this level
TVD_SHIFT = 0.2  # a categorical distribution shifted when this share of the mass moved
LABEL_COLUMNS = ("u", "v", "visibility", "box_size_px", "depth_m", "x_world", "y_world", "z_world")

MAJOR_CONFIG_PREFIXES = ("labels.", "dataset.oks_sigma", "dataset.split.", "camera.intrinsics", "name")
IGNORED_CONFIG_KEYS = ("version",)
PATCH_CONFIG_KEYS = ("description",)


@dataclass
class Shift:
    """One distribution compared between the versions."""

    name: str
    old: dict
    new: dict
    statistic: float  # KS statistic (numbers) or total variation distance (categories)
    shifted: bool


@dataclass
class DatasetDiff:
    old_name: str
    new_name: str
    old_version: str
    new_version: str
    config: list[dict] = field(default_factory=list)  # {"key", "old", "new"}
    schema: list[str] = field(default_factory=list)
    counts: dict = field(default_factory=dict)  # split -> metric -> [old, new]
    images: dict = field(default_factory=dict)  # added, removed, moved, changed, labels_changed
    distributions: list[Shift] = field(default_factory=list)
    reasons: list[tuple[str, str]] = field(default_factory=list)  # (level, why)

    @property
    def bump(self) -> str:
        return max((lvl for lvl, _ in self.reasons), key=LEVELS.index, default="none")

    @property
    def declared(self) -> str:
        return declared_bump(self.old_version, self.new_version)

    @property
    def declared_enough(self) -> bool:
        if self.declared == "downgrade":
            return self.bump == "none"
        return LEVELS.index(self.declared) >= LEVELS.index(self.bump)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["reasons"] = [{"level": lvl, "why": why} for lvl, why in self.reasons]
        d.update(bump=self.bump, declared=self.declared, declared_enough=self.declared_enough)
        return d

    def report(self) -> str:
        """The comparison as text, most important first."""
        out = [
            f"{self.old_name} v{self.old_version} -> {self.new_name} v{self.new_version}",
            f"needs a {self.bump.upper()} version bump"
            + (
                f"; v{self.new_version} is a {self.declared} bump"
                + (" (enough)" if self.declared_enough else " (NOT enough)")
            ),
        ]
        for lvl, why in sorted(self.reasons, key=lambda r: -LEVELS.index(r[0])):
            out.append(f"  {lvl:5s}  {why}")
        out += ["", f"config ({len(self.config)} changes)"]
        out += [f"  {c['key']}: {_short(c['old'])} -> {_short(c['new'])}" for c in self.config] or [
            "  unchanged"
        ]
        out += ["", "schema"] + ([f"  {s}" for s in self.schema] or ["  unchanged"])
        out += ["", "counts per split (old -> new)"]
        for split, m in self.counts.items():
            out.append(
                f"  {split:5s} "
                + ", ".join(
                    f"{k} {o} -> {n}" + (f" ({n - o:+d})" if n != o else "") for k, (o, n) in m.items()
                )
            )
        im = self.images
        out += [
            "",
            f"images: {im.get('added', 0)} added, {im.get('removed', 0)} removed, {im.get('moved', 0)} moved "
            f"between splits, {im.get('changed', 0)} of {im.get('common', 0)} kept changed their pixels, "
            f"{im.get('labels_changed', 0)} their labels",
            "",
            "distributions (old -> new)",
        ]
        same = [s for s in self.distributions if s.statistic == 0 or s.old == s.new]
        for s in sorted((s for s in self.distributions if s not in same), key=lambda s: not s.shifted):
            flag = "SHIFT" if s.shifted else "     "
            out.append(f"  {flag} {s.name}: {_summary(s.old)} -> {_summary(s.new)} (stat {s.statistic:.3g})")
        if same:
            out.append(f"  {len(same)} more unchanged: {', '.join(s.name for s in same)}")
        return "\n".join(out)


def _short(v) -> str:
    text = json.dumps(v) if not isinstance(v, str) else v
    return text if len(text) <= 60 else text[:57] + "..."


def _summary(d: dict) -> str:
    return ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in d.items())


def parse_version(v: str) -> tuple[int, int, int]:
    major, minor, patch = (int(x) for x in v.split("-")[0].split("+")[0].split("."))
    return major, minor, patch


def declared_bump(old: str, new: str) -> str:
    """The bump that going from version ``old`` to ``new`` declares: none, patch, minor, major or downgrade."""
    a, b = parse_version(old), parse_version(new)
    if b == a:
        return "none"
    if b < a:
        return "downgrade"
    if b[0] > a[0]:
        return "major"
    if b[1] > a[1]:
        return "minor"
    return "patch"


def flatten(d, prefix: str = "") -> dict:
    """Nested dicts and lists as dotted keys (``camera.trajectories[0].count``) to leaf values."""
    out = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(d, list) and any(isinstance(x, dict | list) for x in d):
        for i, v in enumerate(d):
            out.update(flatten(v, f"{prefix}[{i}]"))
    else:
        out[prefix] = d
    return out


def _config_changes(old: dict, new: dict) -> list[dict]:
    a, b = flatten(old), flatten(new)
    missing = "(absent)"
    return [
        {"key": k, "old": a.get(k, missing), "new": b.get(k, missing)}
        for k in sorted(set(a) | set(b))
        if a.get(k, missing) != b.get(k, missing)
    ]


def _config_level(key: str, old, new) -> str:
    if key in IGNORED_CONFIG_KEYS:
        return "none"
    if key in PATCH_CONFIG_KEYS:
        return "patch"
    if key.startswith(MAJOR_CONFIG_PREFIXES):
        return "major"
    if key.startswith("dataset.store_") and old is True and new is not True:
        return "major"  # files consumers may read are gone
    return "minor"


def _read(ds: Path) -> tuple[DatasetInfo, pd.DataFrame, pd.DataFrame, dict]:
    try:
        info = DatasetInfo.read(ds)
    except DatasetFormatError as e:
        raise ConfigError(str(e)) from None
    schemas = {}
    frames = []
    for name, rel in (("samples", layout.SAMPLES), ("keypoints", layout.KEYPOINTS)):
        if not (ds / rel).exists():
            raise ConfigError(f"{ds}: no {rel}; accepted: a dataset or published bundle folder")
        try:
            t = layout.read_table(ds / rel)
        except DatasetFormatError as e:
            raise ConfigError(str(e)) from None
        schemas[name] = {f.name: str(f.type) for f in t.schema}
        frames.append(t.to_pandas())
    return info, frames[0], frames[1], schemas


def _schema_changes(d: DatasetDiff, old: DatasetInfo, new: DatasetInfo, sa: dict, sb: dict) -> None:
    if old.schema_version != new.schema_version:
        level = declared_bump(old.schema_version, new.schema_version)
        level = "major" if level == "downgrade" else level
        d.schema.append(f"schema_version {old.schema_version} -> {new.schema_version}")
        d.reasons.append((level, f"schema version {old.schema_version} -> {new.schema_version}"))
    for table in sa:
        a, b = sa[table], sb[table]
        removed = sorted(set(a) - set(b))
        added = sorted(set(b) - set(a))
        retyped = sorted(c for c in set(a) & set(b) if a[c] != b[c])
        for c in removed:
            d.schema.append(f"{table}.{c} removed ({a[c]})")
        for c in added:
            d.schema.append(f"{table}.{c} added ({b[c]})")
        for c in retyped:
            d.schema.append(f"{table}.{c} type {a[c]} -> {b[c]}")
        if removed or retyped:
            d.reasons.append(("major", f"{table}: {len(removed)} columns removed, {len(retyped)} retyped"))
        if added:
            d.reasons.append(("minor", f"{table}: {len(added)} columns added"))


def _info_changes(d: DatasetDiff, old: DatasetInfo, new: DatasetInfo) -> None:
    for name in ("keypoint_names", "oks_sigma", "image_size", "intrinsics", "conventions"):
        if getattr(old, name) != getattr(new, name):
            d.reasons.append(("major", f"label meaning changed: {name}"))
    if old.generator != new.generator:
        d.reasons.append(
            (
                "patch",
                f"generator {old.generator.get('version')} ({str(old.generator.get('git_commit'))[:12]}) -> "
                f"{new.generator.get('version')} ({str(new.generator.get('git_commit'))[:12]})",
            )
        )


def _counts(d: DatasetDiff, old: DatasetInfo, new: DatasetInfo) -> None:
    for split in layout.SPLITS:
        a, b = old.counts.get(split, {}), new.counts.get(split, {})
        d.counts[split] = {k: [int(a.get(k, 0)), int(b.get(k, 0))] for k in sorted(set(a) | set(b))}


def _images(d: DatasetDiff, sa: pd.DataFrame, sb: pd.DataFrame, ka: pd.DataFrame, kb: pd.DataFrame) -> None:
    a, b = sa.set_index("image_id"), sb.set_index("image_id")
    common = a.index.intersection(b.index)
    removed = a.index.difference(b.index)
    moved = [i for i in common if a.at[i, "split"] != b.at[i, "split"]]
    changed = int((a.loc[common, "image_sha256"] != b.loc[common, "image_sha256"]).sum())
    key = ["image_id", "crossing_id"]
    ja = ka[ka.image_id.isin(common)].set_index(key)[list(LABEL_COLUMNS)].sort_index()
    jb = kb[kb.image_id.isin(common)].set_index(key)[list(LABEL_COLUMNS)].sort_index()
    if ja.index.equals(jb.index):
        diff = ~((ja == jb) | (ja.isna() & jb.isna())).all(axis=1)
        labels_changed = int(diff.groupby(level=0).any().sum())
    else:
        labels_changed = len(common)
    d.images = {
        "common": len(common),
        "added": len(b.index.difference(a.index)),
        "removed": len(removed),
        "moved": len(moved),
        "changed": changed,
        "labels_changed": labels_changed,
    }
    eval_removed = int(a.loc[removed, "split"].isin(["val", "test"]).sum())
    if moved:
        d.reasons.append(("major", f"{len(moved)} images moved between splits, e.g. {moved[0]}"))
    if eval_removed:
        d.reasons.append(
            ("major", f"{eval_removed} val/test images removed: evaluation numbers are not comparable")
        )
    if len(removed) - eval_removed:
        d.reasons.append(("minor", f"{len(removed) - eval_removed} train images removed"))
    if d.images["added"]:
        d.reasons.append(("minor", f"{d.images['added']} images added"))
    if labels_changed:
        d.reasons.append(("minor", f"labels of {labels_changed} kept images changed"))
    if changed:
        d.reasons.append(("patch", f"pixels of {changed} kept images changed"))


def _numeric_shift(name: str, a: np.ndarray, b: np.ndarray) -> Shift:
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if len(a) == 0 or len(b) == 0:
        return Shift(name, {"n": len(a)}, {"n": len(b)}, float("nan"), len(a) != len(b))
    ks = stats.ks_2samp(a, b)

    def summary(x: np.ndarray) -> dict:
        return {"mean": float(x.mean()), "min": float(x.min()), "max": float(x.max())}

    return Shift(name, summary(a), summary(b), float(ks.statistic), bool(ks.pvalue < KS_P_SHIFT))


def _category_shift(name: str, a: pd.Series, b: pd.Series) -> Shift:
    pa_, pb = a.astype(str).value_counts(normalize=True), b.astype(str).value_counts(normalize=True)
    cats = sorted(set(pa_.index) | set(pb.index))
    pa_, pb = pa_.reindex(cats, fill_value=0.0), pb.reindex(cats, fill_value=0.0)
    tvd = float(0.5 * np.abs(pa_ - pb).sum())
    return Shift(
        name,
        {k: round(float(v), 3) for k, v in pa_.items()},
        {k: round(float(v), 3) for k, v in pb.items()},
        tvd,
        tvd >= TVD_SHIFT,
    )


def _distributions(
    d: DatasetDiff, sa: pd.DataFrame, sb: pd.DataFrame, ka: pd.DataFrame, kb: pd.DataFrame
) -> None:
    d.distributions.append(
        _numeric_shift(
            "visible keypoints per image", sa.n_visible.to_numpy(float), sb.n_visible.to_numpy(float)
        )
    )
    d.distributions.append(
        _numeric_shift(
            "occluded keypoints per image", sa.n_occluded.to_numpy(float), sb.n_occluded.to_numpy(float)
        )
    )
    names = {0: "outside", 1: "occluded", 2: "visible"}
    d.distributions.append(
        _category_shift("visibility of keypoint rows", ka.visibility.map(names), kb.visibility.map(names))
    )
    cols = [c for c in layout.randomized_columns(sa.columns) if c in sb.columns]
    for c in cols:
        a, b = sa[c], sb[c]
        if (
            pd.api.types.is_bool_dtype(a)
            or not pd.api.types.is_numeric_dtype(a)
            or not pd.api.types.is_numeric_dtype(b)
        ):
            d.distributions.append(_category_shift(c, a, b))
        else:
            d.distributions.append(_numeric_shift(c, a.to_numpy(float), b.to_numpy(float)))
    shifted = [s.name for s in d.distributions if s.shifted]
    if shifted:
        d.reasons.append(("minor", f"{len(shifted)} distributions shifted, e.g. {shifted[0]}"))


def diff_datasets(old: str | Path, new: str | Path) -> DatasetDiff:
    """Compare two versions of a dataset (built folders or published bundles)."""
    ia, sa, ka, schema_a = _read(Path(old))
    ib, sb, kb, schema_b = _read(Path(new))
    d = DatasetDiff(ia.name, ib.name, ia.version, ib.version)
    d.config = _config_changes(ia.config, ib.config)
    for c in d.config:
        level = _config_level(c["key"], c["old"], c["new"])
        if level != "none":
            d.reasons.append((level, f"config {c['key']}: {_short(c['old'])} -> {_short(c['new'])}"))
    if ia.description != ib.description and not any(c["key"] == "description" for c in d.config):
        d.reasons.append(("patch", "description changed"))
    _schema_changes(d, ia, ib, schema_a, schema_b)
    _info_changes(d, ia, ib)
    _counts(d, ia, ib)
    _images(d, sa, sb, ka, kb)
    _distributions(d, sa, sb, ka, kb)
    return d
