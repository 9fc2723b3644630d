"""GLB: the JSON chunk's buffers, views and accessors, against the bytes the file holds.

trimesh allocates every accessor from its declared ``count``, so each chunk must fit the file,
each buffer its BIN chunk or data URI (outside files are refused), each view its buffer and each
accessor (and its sparse part) its view; accessors without data, which the reader fills with zeros,
may take only a bounded multiple of the file's size. Points and faces are then summed over the
meshes that the default scene shows.
"""

from __future__ import annotations

import json
import struct
from typing import Any, BinaryIO

from catalign.geometry.headers._common import GLTF_FILL_EXPANSION, Declared, File

_GLTF_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_GLTF_TYPE_COMPONENTS = {
    "SCALAR": 1,
    "VEC2": 2,
    "VEC3": 3,
    "VEC4": 4,
    "MAT2": 4,
    "MAT3": 9,
    "MAT4": 16,
}
_GLTF_TRIANGLES, _GLTF_STRIP, _GLTF_FAN = 4, 5, 6


def check_glb(f: File, handle: BinaryIO) -> Declared:
    head = handle.read(20)
    if len(head) < 12 or head[:4] != b"glTF":
        raise f.unreadable("it does not start with the GLB magic 'glTF'")
    version, length = struct.unpack("<II", head[4:12])
    if version != 2:
        raise f.unreadable(f"the header declares glTF version {version}; only 2 is read")
    if length != f.size:
        raise f.unreadable(f"the header declares {length} bytes, but the file has {f.size}")
    if len(head) < 20:
        raise f.unreadable("the file ends before its JSON chunk")
    json_bytes, json_type = struct.unpack("<I4s", head[12:20])
    if json_type != b"JSON":
        raise f.unreadable("its first chunk is not JSON")
    if json_bytes > f.size - 20:
        raise f.unreadable(
            f"the header declares a JSON chunk of {json_bytes} bytes, "
            f"but {f.room(f.size - 20)} are fewer"
        )
    try:
        gltf = json.loads(handle.read(json_bytes))
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise f.unreadable(f"its JSON chunk does not parse ({exc})") from None
    if not isinstance(gltf, dict):
        raise f.unreadable("its JSON chunk is not an object")
    bin_bytes = _glb_bin_chunk(f, handle, 20 + json_bytes)
    return _GltfCheck(f, gltf, bin_bytes).run()


def _lookup(table: dict[Any, int], key: object) -> int | None:
    """``table[key]``, or ``None`` for a missing or unhashable key (JSON lists, objects)."""
    return table.get(key) if isinstance(key, int | str) else None


def _glb_bin_chunk(f: File, handle: BinaryIO, position: int) -> int:
    """The length of the BIN chunk (0 without one), after checking every chunk fits the file."""
    bin_bytes = None
    while position + 8 <= f.size:
        handle.seek(position)
        chunk_bytes, chunk_type = struct.unpack("<I4s", handle.read(8))
        if chunk_bytes > f.size - position - 8:
            raise f.unreadable(
                f"the header declares a chunk of {chunk_bytes} bytes, "
                f"but {f.room(f.size - position - 8)} are fewer"
            )
        if chunk_type == b"BIN\x00" and bin_bytes is None:
            bin_bytes = chunk_bytes
        position += 8 + chunk_bytes
    return bin_bytes or 0


class _GltfCheck:
    """Buffers within the file, views within buffers, accessors within views; then the counts."""

    def __init__(self, f: File, gltf: dict[str, Any], bin_bytes: int) -> None:
        self.f = f
        self.gltf = gltf
        self.bin_bytes = bin_bytes

    def run(self) -> Declared:
        buffers = [self._buffer(i, b) for i, b in enumerate(self._list("buffers"))]
        views = [self._view(i, v, buffers) for i, v in enumerate(self._list("bufferViews"))]
        counts = [self._accessor(i, a, views) for i, a in enumerate(self._list("accessors"))]
        for i, image in enumerate(self._list("images")):
            self._not_outside(image, f"image {i}")
        points, faces = self._mesh_counts(counts)
        return self.f.within_limits(points, faces)

    def _list(self, key: str) -> list[dict[str, Any]]:
        items = self.gltf.get(key, [])
        if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
            raise self.f.unreadable(f"its JSON '{key}' is not a list of objects")
        return items

    def _int(self, obj: dict[str, Any], key: str, where: str, default: int | None = None) -> int:
        value = obj.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise self.f.unreadable(f"{where} has no whole, non-negative {key}")
        return value

    def _index(
        self, obj: dict[str, Any], key: str, where: str, length: int, default: int | None = None
    ) -> int:
        value = self._int(obj, key, where, default)
        if value >= length:
            raise self.f.unreadable(f"{where} refers to {key} {value}, which does not exist")
        return value

    def _not_outside(self, obj: dict[str, Any], where: str) -> None:
        uri = obj.get("uri")
        if uri is not None and not (isinstance(uri, str) and uri.startswith("data:")):
            raise self.f.unreadable(f"{where} refers to an outside file ({uri!r})")

    def _buffer(self, index: int, buffer: dict[str, Any]) -> int:
        where = f"buffer {index}"
        declared = self._int(buffer, "byteLength", where)
        self._not_outside(buffer, where)
        uri = buffer.get("uri")
        available = self.bin_bytes if uri is None else len(uri) * 3 // 4
        if declared > available:
            holder = "the BIN chunk" if uri is None else "its data URI"
            raise self.f.unreadable(
                f"the header declares {where} of {declared} bytes, "
                f"but {holder} holds at most {available}"
            )
        return declared

    def _view(self, index: int, view: dict[str, Any], buffers: list[int]) -> int:
        where = f"bufferView {index}"
        buffer = self._index(view, "buffer", where, len(buffers))
        offset = self._int(view, "byteOffset", where, 0)
        length = self._int(view, "byteLength", where)
        if offset + length > buffers[buffer]:
            raise self.f.unreadable(
                f"the header declares {where} of {length} bytes at offset {offset}, "
                f"but buffer {buffer} holds {buffers[buffer]}"
            )
        return index

    def _accessor(self, index: int, accessor: dict[str, Any], views: list[int]) -> int:
        where = f"accessor {index}"
        count = self._int(accessor, "count", where)
        item = self._item_bytes(accessor, where)
        if "bufferView" in accessor:
            offset = self._int(accessor, "byteOffset", where, 0)
            self._fits_view(accessor, where, count, item, offset)
        else:  # filled with zeros by the reader: allowed only in proportion to the file
            if count * item > GLTF_FILL_EXPANSION * self.f.size:
                raise self.f.unreadable(
                    f"the header declares {where} of {count} values without data, which would "
                    f"take {count * item} bytes, more than {GLTF_FILL_EXPANSION} times the "
                    f"file's {self.f.size} bytes"
                )
        sparse = accessor.get("sparse")
        if isinstance(sparse, dict):
            sparse_count = self._int(sparse, "count", f"{where}'s sparse part")
            for part, width in (("indices", None), ("values", item)):
                block = sparse.get(part)
                if not isinstance(block, dict):
                    raise self.f.unreadable(f"{where}'s sparse part has no {part}")
                if width is None:
                    width = _lookup(_GLTF_COMPONENT_BYTES, block.get("componentType")) or 4
                offset = self._int(block, "byteOffset", f"{where}'s sparse {part}", 0)
                self._fits_view(block, f"{where}'s sparse {part}", sparse_count, width, offset)
        return count

    def _item_bytes(self, accessor: dict[str, Any], where: str) -> int:
        component = _lookup(_GLTF_COMPONENT_BYTES, accessor.get("componentType"))
        components = _lookup(_GLTF_TYPE_COMPONENTS, accessor.get("type"))
        if component is None or components is None:
            raise self.f.unreadable(f"{where} has an unknown componentType or type")
        return component * components

    def _fits_view(
        self, obj: dict[str, Any], where: str, count: int, item: int, offset: int
    ) -> None:
        views = self._list("bufferViews")
        index = self._index(obj, "bufferView", where, len(views))
        view = views[index]
        stride = self._int(view, "byteStride", f"bufferView {index}", 0) or item
        need = offset + (count - 1) * stride + item if count else 0
        if need > view["byteLength"]:
            raise self.f.unreadable(
                f"the header declares {where} of {count} values of {item} bytes, which need "
                f"{need} bytes, but bufferView {index} holds {view['byteLength']}"
            )

    def _mesh_counts(self, counts: list[int]) -> tuple[int, int]:
        """Points (POSITION values) and triangles, once for every node that shows a mesh."""
        per_mesh = []
        for i, mesh in enumerate(self._list("meshes")):
            primitives = mesh.get("primitives", [])
            if not isinstance(primitives, list) or not all(isinstance(p, dict) for p in primitives):
                raise self.f.unreadable(f"mesh {i} has no list of primitives")
            points = faces = 0
            for p in primitives:
                attributes = p.get("attributes", {})
                if not isinstance(attributes, dict):
                    raise self.f.unreadable(f"a primitive of mesh {i} has no attributes object")
                n = counts[self._index(attributes, "POSITION", f"mesh {i}", len(counts))]
                points += n
                if "indices" in p:
                    n = counts[self._index(p, "indices", f"mesh {i}", len(counts))]
                mode = p.get("mode", _GLTF_TRIANGLES)
                if mode == _GLTF_TRIANGLES:
                    faces += n // 3
                elif mode in (_GLTF_STRIP, _GLTF_FAN):
                    faces += max(n - 2, 0)
            per_mesh.append((points, faces))
        shown = self._shown_meshes(len(per_mesh))
        return (
            sum(per_mesh[m][0] for m in shown),
            sum(per_mesh[m][1] for m in shown),
        )

    def _shown_meshes(self, n_meshes: int) -> list[int]:
        """The mesh of every node reachable from the default scene; every mesh without scenes."""
        nodes = self._list("nodes")
        scenes = self._list("scenes")
        if not scenes:
            return list(range(n_meshes))
        chosen = self._index(self.gltf, "scene", "the file", len(scenes), default=0)
        roots = scenes[chosen].get("nodes", [])
        pending = list(roots) if isinstance(roots, list) else []
        seen: set[int] = set()
        shown = []
        while pending:
            index = pending.pop()
            if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(nodes):
                raise self.f.unreadable(f"the scene refers to node {index!r}, which does not exist")
            if index in seen:
                continue
            seen.add(index)
            node = nodes[index]
            if "mesh" in node:
                shown.append(self._index(node, "mesh", f"node {index}", n_meshes))
            children = node.get("children", [])
            if isinstance(children, list):
                pending.extend(children)
        return shown
