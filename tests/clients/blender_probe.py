"""Run inside a Python with Blender's ``bpy``: import a glTF file with Blender's own importer and
write a report (import messages, meshes, materials, UVs, normals, and every mesh's evaluated
world-space vertex positions at the given times, in glTF's Y-up axes) as an .npz.

    python blender_probe.py FILE.glb OUT.npz CLIP TIME [TIME ...]
"""
import io
import json
import sys
from contextlib import redirect_stdout

import bpy
import numpy as np

path, out, clip = sys.argv[1], sys.argv[2], sys.argv[3]
times = [float(t) for t in sys.argv[4:]]
bpy.ops.wm.read_factory_settings(use_empty=True)
log = io.StringIO()
with redirect_stdout(log):
    result = bpy.ops.import_scene.gltf(filepath=path)
scene = bpy.context.scene
fps = scene.render.fps / scene.render.fps_base
actions = [a.name for a in bpy.data.actions]
# Blender 5's importer makes one layered action per clip, with a slot per animated object
chosen = [a for a in bpy.data.actions if a.name == clip or a.name.startswith(clip + "_")]
if not chosen:
    sys.exit(f"no action {clip!r} among {actions}")
for ob in scene.objects:
    if ob.animation_data is None:
        continue
    for a in chosen:
        slots = [s for s in getattr(a, "slots", ()) if s.target_id_type == "OBJECT" and s.name_display == ob.name]
        if slots or not getattr(a, "slots", ()):
            ob.animation_data.action = a
            if slots:
                ob.animation_data.action_slot = slots[0]
            break
meshes = [ob for ob in scene.objects if ob.type == "MESH" and ob.users_collection and ob.visible_get()]
to_gltf = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=np.float64)   # Blender Z-up -> glTF Y-up
arrays = {}
for i, t in enumerate(times):
    frame = t * fps
    scene.frame_set(int(np.floor(frame)), subframe=float(frame - np.floor(frame)))
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for m, ob in enumerate(meshes):
        ev = ob.evaluated_get(depsgraph)
        mesh = ev.to_mesh()
        co = np.empty(3 * len(mesh.vertices))
        mesh.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3) @ np.array(ev.matrix_world)[:3, :3].T + np.array(ev.matrix_world)[:3, 3]
        arrays[f"positions_{i}_{m}"] = co @ to_gltf.T
        ev.to_mesh_clear()
info = [{"name": ob.name, "vertices": len(ob.data.vertices), "uv_layers": len(ob.data.uv_layers),
         "materials": [s.material.name for s in ob.material_slots if s.material],
         "textured": any(n.type == "TEX_IMAGE" for s in ob.material_slots if s.material and s.material.node_tree
                         for n in s.material.node_tree.nodes),
         "custom_normals": bool(ob.data.has_custom_normals), "shape_keys": len(ob.data.shape_keys.key_blocks)
         if ob.data.shape_keys else 0} for ob in meshes]
np.savez(out, report=json.dumps({"result": sorted(result), "log": log.getvalue(), "fps": fps,
                                  "actions": actions, "meshes": info, "times": times}), **arrays)
