"""glTF 2.0 written by the specification for the mesh-import tests, independent of trimesh's exporter."""

import json

import numpy as np


def gltf_document(primitives: list[tuple[str, np.ndarray, np.ndarray]]) -> tuple[dict, bytes]:
    """The JSON document and binary buffer of one mesh whose primitives are (material name, positions
    (N, 3) as the file stores them, triangles (M, 3)), one node, one scene; the buffer has no uri yet."""
    blob, views, accessors, prims = b"", [], [], []
    for i, (_, positions, faces) in enumerate(primitives):
        for data, kind, target in ((positions, "VEC3", 34962), (faces, "SCALAR", 34963)):
            raw = np.ascontiguousarray(data, dtype=np.float32 if kind == "VEC3" else np.uint32).tobytes()
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(raw), "target": target})
            accessor = {"bufferView": len(views) - 1, "componentType": 5126 if kind == "VEC3" else 5125, "type": kind}
            accessor["count"] = len(positions) if kind == "VEC3" else np.asarray(faces).size
            if kind == "VEC3":
                accessor |= {"min": np.min(positions, axis=0).tolist(), "max": np.max(positions, axis=0).tolist()}
            accessors.append(accessor)
            blob += raw + b"\0" * (-len(raw) % 4)
        prims.append({"attributes": {"POSITION": 2 * i}, "indices": 2 * i + 1, "material": i, "mode": 4})
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "building"}],
        "meshes": [{"primitives": prims}],
        "materials": [{"name": name} for name, _, _ in primitives],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
    }
    return doc, blob


def gltf_text(doc: dict) -> bytes:
    """The document as a GLB JSON chunk wants it: UTF-8, padded with spaces to 4 bytes."""
    text = json.dumps(doc).encode()
    return text + b" " * (-len(text) % 4)
