"""The Blender anchor of the e2e suite: the whole job nrpose's ``pose`` does, in Blender.

    PYTHON_WITH_BPY blender_bake.py CHARACTER.glb CLIP FPS FRAMES OUT.npz

Runs in the project's ``bpy`` environment (.venv-blender, `make blender`), not in
nrpose's: it imports nothing of nrpose. Imports the .glb (Blender's glTF importer),
plays the animation named CLIP on every armature at FPS frames per second for FRAMES
frames (times k / FPS, k = 0 .. FRAMES - 1, as ``nrpose pose --clip CLIP --fps FPS``
samples the clip), reads back every frame's evaluated (armature-deformed) vertices of
every skinned mesh in world space, converts them from Blender's Z-up to glTF's Y-up
axes, and writes OUT.npz with, per mesh i (in order of the mesh data names),
``positions_i`` (FRAMES, V_i, 3) float32 metres, and ``names`` (the mesh data names).
Its last line on stdout: JSON seconds of its stages (import_bpy, import_gltf, play, write).
One line on stderr and exit status 2 when the clip is missing.
"""
import json
import sys
import time

import numpy as np

T0 = time.perf_counter()
import bpy  # noqa: E402

T_BPY = time.perf_counter()


def main(argv) -> int:
    glb, clip, fps, count, out = argv[0], argv[1], int(argv[2]), int(argv[3]), argv[4]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = fps, 1.0   # keys land on frame = time * fps
    # the importer makes the file's first animation active and evaluates it, which leaves
    # that animation's values on the joints CLIP does not animate; glTF keeps them at their
    # node transforms, where the importer put them before: make no animation active
    from io_scene_gltf2.blender.imp.animation import BlenderAnimation
    BlenderAnimation.restore_animation = staticmethod(lambda gltf, name: None)
    bpy.ops.import_scene.gltf(filepath=glb, disable_bone_shape=True, loglevel=50)
    t_gltf = time.perf_counter()
    action = bpy.data.actions.get(clip)
    if action is None:
        print(f"blender_bake: {glb} has no animation {clip!r}", file=sys.stderr)
        return 2
    for ob in bpy.data.objects:
        if ob.type == "ARMATURE":
            ad = ob.animation_data or ob.animation_data_create()
            ad.action = action
            if getattr(ad, "action_slot", None) is None and getattr(action, "slots", None):
                ad.action_slot = action.slots[0]
    meshes = sorted((ob for ob in scene.objects if ob.type == "MESH"
                     and any(m.type == "ARMATURE" for m in ob.modifiers)), key=lambda ob: ob.data.name)
    frames = [np.empty((count, len(ob.data.vertices), 3), np.float32) for ob in meshes]
    axes = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])   # Blender (x, y, z) -> glTF (x, z, -y)
    for k in range(count):
        scene.frame_set(k)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        for ob, buf in zip(meshes, frames):
            ev = ob.evaluated_get(depsgraph)
            me = ev.to_mesh()
            co = np.empty(len(me.vertices) * 3, np.float32)
            me.vertices.foreach_get("co", co)
            ev.to_mesh_clear()
            m = np.array(ev.matrix_world, dtype=np.float64)
            world = co.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3]
            buf[k] = world @ axes.T
    t_play = time.perf_counter()
    np.savez(out, names=np.array([ob.data.name for ob in meshes]),
             **{f"positions_{i}": f for i, f in enumerate(frames)})
    print(json.dumps({"import_bpy": T_BPY - T0, "import_gltf": t_gltf - T_BPY, "play": t_play - t_gltf,
                      "write": time.perf_counter() - t_play}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
