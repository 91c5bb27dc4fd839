"""Croissant metadata (MLCommons, version 1.1) of a release bundle: its files, record sets and fields.

Three record sets describe the data: ``default`` (the ready-to-train rows of ``data/*.parquet``, one per
image with the image embedded and its keypoints nested), ``samples`` and ``keypoints`` (the full source
tables: every randomized scene and sensor parameter, and every crossing per image, also those outside
the view). Fields are generated from the Parquet schemas, so the metadata always matches the files;
field descriptions come from the dataset contract in ``schemas/tables``.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from rebar_data.dataset import layout
from rebar_data.dataset.layout import DatasetInfo
from rebar_data.publish.rows import DATA_DIR, KEYPOINT_FIELDS, ROW_FIELDS

CROISSANT_VERSION = "http://mlcommons.org/croissant/1.1"
CONTEXT = {
    "@language": "en",
    "@vocab": "https://schema.org/",
    "arrayShape": "cr:arrayShape",
    "citeAs": "cr:citeAs",
    "column": "cr:column",
    "conformsTo": "dct:conformsTo",
    "containedIn": "cr:containedIn",
    "cr": "http://mlcommons.org/croissant/",
    "rai": "http://mlcommons.org/croissant/RAI/",
    "data": {"@id": "cr:data", "@type": "@json"},
    "dataType": {"@id": "cr:dataType", "@type": "@vocab"},
    "dct": "http://purl.org/dc/terms/",
    "equivalentProperty": "cr:equivalentProperty",
    "examples": {"@id": "cr:examples", "@type": "@json"},
    "extract": "cr:extract",
    "field": "cr:field",
    "fileProperty": "cr:fileProperty",
    "fileObject": "cr:fileObject",
    "fileSet": "cr:fileSet",
    "format": "cr:format",
    "includes": "cr:includes",
    "isArray": "cr:isArray",
    "isLiveDataset": "cr:isLiveDataset",
    "jsonPath": "cr:jsonPath",
    "key": "cr:key",
    "md5": "cr:md5",
    "parentField": "cr:parentField",
    "path": "cr:path",
    "recordSet": "cr:recordSet",
    "references": "cr:references",
    "regex": "cr:regex",
    "repeated": "cr:repeated",
    "replace": "cr:replace",
    "samplingRate": "cr:samplingRate",
    "sc": "https://schema.org/",
    "separator": "cr:separator",
    "source": "cr:source",
    "subField": "cr:subField",
    "transform": "cr:transform",
}
PARQUET = "application/x-parquet"
# Croissant's well-known split of each of the dataset's splits
SPLIT_URLS = {"train": "cr:TrainingSplit", "val": "cr:ValidationSplit", "test": "cr:TestSplit"}


def data_type(t: pa.DataType) -> str:
    """The Croissant data type of an Arrow scalar type."""
    if pa.types.is_boolean(t):
        return "sc:Boolean"
    for check, name in (
        (pa.types.is_int8, "cr:Int8"),
        (pa.types.is_int16, "cr:Int16"),
        (pa.types.is_int32, "cr:Int32"),
        (pa.types.is_int64, "cr:Int64"),
        (pa.types.is_float32, "cr:Float32"),
        (pa.types.is_float64, "cr:Float64"),
    ):
        if check(t):
            return name
    if pa.types.is_string(t) or pa.types.is_large_string(t):
        return "sc:Text"
    raise ValueError(f"no Croissant data type for Arrow type {t}")


def _is_list(t: pa.DataType) -> bool:
    return pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t)


def field(
    record_set: str,
    name: str,
    t: pa.DataType,
    source: dict,
    description: str,
    *,
    json_path: str | None = None,
) -> dict:
    """A ``cr:Field`` for a column, or for a struct member (``json_path``) inside ``source``'s column."""
    fid = f"{record_set}/{name}"
    f: dict = {"@type": "cr:Field", "@id": fid, "name": name, "description": description}
    if _is_list(t):
        f["isArray"] = True
        f["arrayShape"] = str(t.list_size) if pa.types.is_fixed_size_list(t) else "-1"
        t = t.value_type
    if json_path is None:
        source = {**source, "extract": {"column": name}}
    else:
        source = {**source, "transform": {"jsonPath": json_path}}
    if pa.types.is_struct(t):
        f["subField"] = [
            field(fid, c.name, c.type, source, _member_description(name, c.name), json_path=c.name) for c in t
        ]
        return f
    f["dataType"] = data_type(t)
    f["source"] = source
    return f


def _member_description(parent: str, name: str) -> str:
    if parent == "keypoints":
        return {n: d for n, _, d in KEYPOINT_FIELDS}.get(name, name)
    return name


def _table_fields(record_set: str, schema: pa.Schema, source: dict, meanings: dict[str, str]) -> list[dict]:
    return [
        field(record_set, f.name, f.type, source, meanings.get(f.name) or _prefix_meaning(f.name))
        for f in schema
    ]


def _prefix_meaning(name: str) -> str:
    prefix = name.split("_", 1)[0]
    what = {
        "light": "randomized lighting of the scene",
        "mat": "randomized rebar material of the scene",
        "surr": "randomized surroundings of the scene",
        "sensor": "randomized sensor effect of the frame",
    }.get(prefix, "column of the table")
    return f"{what} ({name})"


def default_record_set(schema: pa.Schema) -> list[dict]:
    """The splits record set and ``default``: one record per image from the Parquet shards."""
    src = {"fileSet": {"@id": "parquet-shards"}}
    meanings = {n: d for n, _, d in ROW_FIELDS}
    fields = [
        {
            "@type": "cr:Field",
            "@id": "default/split",
            "name": "split",
            "description": "the split of the record (the shard's name): train, val or test",
            "dataType": "sc:Text",
            "references": {"field": {"@id": "splits/split_name"}},
            "source": {
                **src,
                "extract": {"fileProperty": "fullpath"},
                "transform": {
                    # the split is the shard's name; the regex also accepts the bare name it yields
                    "regex": f"^(?:.*/)?({'|'.join(layout.SPLITS)})(?:-[0-9]+-of-[0-9]+\\.parquet)?$"
                },
            },
        },
        {
            "@type": "cr:Field",
            "@id": "default/image",
            "name": "image",
            "description": meanings["image"],
            "dataType": "sc:ImageObject",
            "source": {**src, "extract": {"column": "image"}, "transform": {"jsonPath": "bytes"}},
        },
    ]
    fields += [
        field("default", f.name, f.type, src, meanings.get(f.name, f.name))
        for f in schema
        if f.name != "image"
    ]
    splits = {
        "@type": "cr:RecordSet",
        "@id": "splits",
        "name": "splits",
        "description": "the splits of the default record set, named as in the source dataset",
        "dataType": "cr:Split",
        "key": {"@id": "splits/split_name"},
        "field": [
            {
                "@type": "cr:Field",
                "@id": "splits/split_name",
                "name": "split_name",
                "description": "the name of the split",
                "dataType": "sc:Text",
            },
            {
                "@type": "cr:Field",
                "@id": "splits/split_url",
                "name": "split_url",
                "description": "Croissant's well-known split it is",
                "dataType": "sc:URL",
            },
        ],
        "data": [{"splits/split_name": s, "splits/split_url": SPLIT_URLS[s]} for s in layout.SPLITS],
    }
    default = {
        "@type": "cr:RecordSet",
        "@id": "default",
        "name": "default",
        "description": "one record per image: the image, its camera and every crossing inside it",
        "key": {"@id": "default/image_id"},
        "field": fields,
    }
    return [splits, default]


def croissant_metadata(
    bundle: Path,
    info: DatasetInfo,
    *,
    description: str,
    license_url: str,
    cite_as: str,
    date_published: str,
    files: dict[str, dict],
    meanings: dict[str, dict[str, str]],
) -> dict:
    """The JSON-LD of ``croissant.json`` for the bundle at ``bundle``.

    Args:
        files: relative path -> {"sha256", "bytes", "encodingFormat", "description"} of every single file
            the metadata lists (tables, info, annotations, data.yaml, the card).
        meanings: table name -> column -> meaning, from the dataset contract.
    """
    distribution = [
        {
            "@type": "cr:FileObject",
            "@id": rel,
            "name": rel,
            "description": f["description"],
            "contentUrl": rel,
            "contentSize": f"{f['bytes']} B",
            "encodingFormat": f["encodingFormat"],
            "sha256": f["sha256"],
        }
        for rel, f in sorted(files.items())
    ]
    distribution += [
        {
            "@type": "cr:FileSet",
            "@id": "parquet-shards",
            "name": "parquet-shards",
            "description": "ready-to-train rows with the images embedded, in the Hugging Face datasets layout",
            "encodingFormat": PARQUET,
            "includes": f"{DATA_DIR}/*.parquet",
        },
        {
            "@type": "cr:FileSet",
            "@id": "images",
            "name": "images",
            "description": "the RGB images as PNG files (the YOLO and COCO views)",
            "encodingFormat": "image/png",
            "includes": "images/*/*.png",
        },
        {
            "@type": "cr:FileSet",
            "@id": "yolo-labels",
            "name": "yolo-labels",
            "description": "Ultralytics YOLO pose labels, one file per image: 0 cx cy w h px py v, normalised",
            "encodingFormat": "text/plain",
            "includes": "labels/*/*.txt",
        },
    ]
    shard = sorted((bundle / DATA_DIR).glob("*.parquet"))[0]
    record_sets = default_record_set(pq.read_schema(shard))
    for table in ("samples", "keypoints"):
        rel = f"tables/{table}.parquet"
        record_sets.append(
            {
                "@type": "cr:RecordSet",
                "@id": table,
                "name": table,
                "description": {
                    "samples": "the source table of images: camera, trajectory, scene and every randomized parameter",
                    "keypoints": "the source table of keypoints: every crossing per image, also those outside it",
                }[table],
                "field": _table_fields(
                    table, pq.read_schema(bundle / rel), {"fileObject": {"@id": rel}}, meanings.get(table, {})
                ),
            }
        )
    return {
        "@context": CONTEXT,
        "@type": "sc:Dataset",
        "conformsTo": CROISSANT_VERSION,
        "name": info.name,
        "description": description,
        "version": info.version,
        "license": license_url,
        "citeAs": cite_as,
        "datePublished": date_published,
        "url": "README.md",
        "keywords": ["synthetic data", "rebar", "keypoint detection", "robotics", "construction", "Open3D"],
        "isAccessibleForFree": True,
        "creator": {
            "@type": "sc:Organization",
            "name": f"{info.generator.get('name', 'rebar-data')} generator",
        },
        "distribution": distribution,
        "recordSet": record_sets,
    }
