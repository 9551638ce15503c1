"""A small game asset as a glTF file, for the tests of posed copies.

A square tube along +y (4 flat sides: every side has its own vertices, so the normals are
split at the 4 hard edges), skinned to two joints (``hip`` at the origin, ``knee`` at y = 1,
the tube's lower 2 rings on the hip alone, the upper 2 on the knee alone, blended in between),
in two primitives with two materials (the seam ring is duplicated), with NORMAL, TANGENT,
TEXCOORD_0, TEXCOORD_1, COLOR_0 and a custom ``_ID`` attribute; a textured material whose
image is an external PNG (``.gltf``) or in the binary chunk (``.glb``); a sampler; a static
``pedestal`` mesh beside it; extras and an optional extension nrpose does not know; a clip
``bend`` turning the knee by 90 degrees about z.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pygltflib
from PIL import Image

RINGS = (0.0, 0.5, 1.0, 1.5, 2.0)   # heights; the seam between the primitives is at y = 1
CORNERS = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64) * 0.25   # (x, z)


def png_bytes() -> bytes:
    """A 4x4 orange-and-white checker PNG."""
    pixels = np.zeros((4, 4, 3), np.uint8)
    pixels[:] = (240, 110, 20)
    pixels[::2, ::2] = pixels[1::2, 1::2] = (250, 250, 250)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, format="PNG")
    return out.getvalue()


def tube_part(heights):
    """Positions, normals, tangents, uv of a square tube between ``heights``; faces."""
    P, N, T, UV, F = [], [], [], [], []
    for side in range(4):
        a, b = CORNERS[side], CORNERS[(side + 1) % 4]
        mid = (a + b) / 2
        normal = np.array([mid[0], 0, mid[1]]) / np.linalg.norm(mid)
        tangent = np.array([b[0] - a[0], 0, b[1] - a[1]]) / np.linalg.norm(b - a)
        base = len(P)
        for r, y in enumerate(heights):
            for c, corner in enumerate((a, b)):
                P.append([corner[0], y, corner[1]])
                N.append(normal)
                T.append([*tangent, 1.0])
                UV.append([(side + c) / 4, y / 2])
        for r in range(len(heights) - 1):
            i = base + 2 * r
            F += [[i, i + 3, i + 1], [i, i + 2, i + 3]]   # counter-clockwise from outside
    return (np.array(P, np.float32), np.array(N, np.float32), np.array(T, np.float32),
            np.array(UV, np.float32), np.array(F, np.uint16))


def knee_weight(y: np.ndarray) -> np.ndarray:
    """Weight of the knee joint by height: 0 up to y = 0.5, 1 from y = 1.5."""
    return np.clip(y - 0.5, 0.0, 1.0)


def build(path: Path, required: list[str] | None = None) -> Path:
    """Write the asset to ``path`` (.glb or .gltf; a .gltf gets ``texture.png`` beside it)."""
    path = Path(path)
    blob = bytearray()
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0", generator="nrpose tests", copyright="CC0"))

    def view(data: bytes, target=None) -> int:
        while len(blob) % 4:
            blob.append(0)
        gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data),
                                                     target=target))
        blob.extend(data)
        return len(gltf.bufferViews) - 1

    def accessor(array, ctype, kind, minmax=False, normalized=None, target=pygltflib.ARRAY_BUFFER) -> int:
        a = np.ascontiguousarray(array)
        acc = pygltflib.Accessor(bufferView=view(a.tobytes(), target), componentType=ctype, count=len(a),
                                 type=kind, normalized=normalized)
        if minmax:
            flat = a.reshape(len(a), -1)
            acc.min, acc.max = flat.min(axis=0).tolist(), flat.max(axis=0).tolist()
        gltf.accessors.append(acc)
        return len(gltf.accessors) - 1

    primitives = []
    for material, heights in enumerate((RINGS[:3], RINGS[2:])):
        P, N, T, UV, F = tube_part(heights)
        w = knee_weight(P[:, 1].astype(np.float64))
        joints = np.zeros((len(P), 4), np.uint8)
        joints[:, 1] = 1
        weights = np.zeros((len(P), 4), np.float32)
        weights[:, 0], weights[:, 1] = 1 - w, w
        colours = np.tile(np.array([[1.0, 0.5, 0.25, 1.0]], np.float32), (len(P), 1))
        attrs = pygltflib.Attributes(
            POSITION=accessor(P, pygltflib.FLOAT, "VEC3", minmax=True), NORMAL=accessor(N, pygltflib.FLOAT, "VEC3"),
            TANGENT=accessor(T, pygltflib.FLOAT, "VEC4"), TEXCOORD_0=accessor(UV, pygltflib.FLOAT, "VEC2"),
            TEXCOORD_1=accessor(UV[:, ::-1].copy(), pygltflib.FLOAT, "VEC2"),
            COLOR_0=accessor(colours, pygltflib.FLOAT, "VEC4"),
            JOINTS_0=accessor(joints, pygltflib.UNSIGNED_BYTE, "VEC4"),
            WEIGHTS_0=accessor(weights, pygltflib.FLOAT, "VEC4"))
        attrs._ID = accessor(np.arange(len(P), dtype=np.float32), pygltflib.FLOAT, "SCALAR")
        primitives.append(pygltflib.Primitive(
            attributes=attrs, material=material, mode=pygltflib.TRIANGLES,
            indices=accessor(F.reshape(-1), pygltflib.UNSIGNED_SHORT, "SCALAR",
                             target=pygltflib.ELEMENT_ARRAY_BUFFER),
            extras={"part": ["thigh", "shin"][material]}))
    pedestal, pedestal_normals, _, _, pedestal_faces = tube_part((-0.4, -0.1))
    pedestal = pedestal * np.float32([3, 1, 3]) + np.float32([0, 0, 0])
    ibm = np.stack([np.eye(4), np.eye(4)])
    ibm[1][1, 3] = -1.0   # the knee sits at y = 1
    gltf.meshes = [
        pygltflib.Mesh(name="leg", primitives=primitives, extras={"author": "tests"}),
        pygltflib.Mesh(name="pedestal", primitives=[pygltflib.Primitive(
            attributes=pygltflib.Attributes(POSITION=accessor(pedestal, pygltflib.FLOAT, "VEC3", minmax=True),
                                            NORMAL=accessor(pedestal_normals, pygltflib.FLOAT, "VEC3")),
            indices=accessor(pedestal_faces.reshape(-1), pygltflib.UNSIGNED_SHORT, "SCALAR",
                             target=pygltflib.ELEMENT_ARRAY_BUFFER), material=1)])]
    gltf.nodes = [
        pygltflib.Node(name="rig", children=[1, 3]),
        pygltflib.Node(name="hip", children=[2]),
        pygltflib.Node(name="knee", translation=[0, 1, 0]),
        pygltflib.Node(name="leg", mesh=0, skin=0, extras={"kind": "character"}),
        pygltflib.Node(name="pedestal", mesh=1, translation=[2, 0, 0],
                       extensions={"EXT_tests_unknown": {"note": "kept"}})]
    gltf.skins = [pygltflib.Skin(joints=[1, 2], inverseBindMatrices=accessor(
        ibm.transpose(0, 2, 1).reshape(2, 16).astype(np.float32), pygltflib.FLOAT, "MAT4", target=None))]
    gltf.scenes, gltf.scene = [pygltflib.Scene(nodes=[0, 4])], 0
    image = png_bytes()
    if path.suffix == ".gltf":
        (path.parent / "texture.png").write_bytes(image)
        gltf.images = [pygltflib.Image(uri="texture.png")]
    else:
        gltf.images = [pygltflib.Image(bufferView=view(image), mimeType="image/png")]
    gltf.samplers = [pygltflib.Sampler(magFilter=9728, minFilter=9728, wrapS=33071, wrapT=33071)]
    gltf.textures = [pygltflib.Texture(source=0, sampler=0)]
    gltf.materials = [
        pygltflib.Material(name="skin", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
            baseColorTexture=pygltflib.TextureInfo(index=0), metallicFactor=0.0),
            occlusionTexture=pygltflib.OcclusionTextureInfo(index=0, texCoord=1, strength=0.3),
            extensions={"KHR_materials_emissive_strength": {"emissiveStrength": 2.0}}),
        pygltflib.Material(name="stone", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
            baseColorFactor=[0.5, 0.5, 0.55, 1.0], metallicFactor=0.0), extras={"surface": "stone"})]
    times = np.array([0.0, 0.5, 1.0], np.float32)
    turn = np.array([[0, 0, 0, 1], [0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)],
                     [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]], np.float32)
    gltf.animations = [pygltflib.Animation(name="bend", samplers=[pygltflib.AnimationSampler(
        input=accessor(times, pygltflib.FLOAT, "SCALAR", minmax=True, target=None),
        output=accessor(turn, pygltflib.FLOAT, "VEC4", target=None), interpolation="LINEAR")],
        channels=[pygltflib.AnimationChannel(sampler=0, target=pygltflib.AnimationChannelTarget(
            node=2, path="rotation"))])]
    gltf.extensionsUsed = ["KHR_materials_emissive_strength", "EXT_tests_unknown", *(required or [])]
    gltf.extensionsRequired = list(required or [])
    gltf.extras = {"scene_note": "kept"}
    gltf.buffers = [pygltflib.Buffer(byteLength=len(blob))]
    if path.suffix == ".gltf":
        (path.parent / "asset.bin").write_bytes(bytes(blob))
        gltf.buffers[0].uri = "asset.bin"
        path.write_text(gltf.to_json())
    else:
        gltf.set_binary_blob(bytes(blob))
        gltf.save_binary(str(path))
    return path
