"""Run inside Blender (``blender -b --python tests/blender_playback.py -- FILE.glb TIMES OUT.json``): import
a .glb with Blender's own glTF importer and write what Blender sees (objects, shape keys, bones, actions)
and the evaluated mesh's world-space vertices at each time (seconds), as JSON."""

import json
import sys

import bpy
import numpy

if not hasattr(numpy, "bool"):  # Debian's Blender 3.4 importer still says np.bool (removed in NumPy 1.24)
    numpy.bool = bool

path, times, out = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=path)
scene = bpy.context.scene
mesh = next(o for o in bpy.data.objects if o.type == "MESH")
keys = mesh.data.shape_keys
armature = next((o for o in bpy.data.objects if o.type == "ARMATURE"), None)
seen = {
    "objects": sorted(o.type for o in bpy.data.objects),
    "shape_keys": [k.name for k in keys.key_blocks[1:]] if keys else [],
    "bones": [b.name for b in armature.data.bones] if armature else [],
    "actions": sorted(len(a.fcurves) for a in bpy.data.actions),
    "fps": scene.render.fps / scene.render.fps_base,
    "vertices": {},
}
for t in map(float, times.split(",")):
    # The importer keys time t at frame t * fps; frame_set takes the integer frame and a subframe.
    frame = t * seen["fps"]
    scene.frame_set(int(frame), subframe=frame - int(frame))
    evaluated = mesh.evaluated_get(bpy.context.evaluated_depsgraph_get())
    data = evaluated.to_mesh()
    seen["vertices"][str(t)] = [list(mesh.matrix_world @ v.co) for v in data.vertices]
    evaluated.to_mesh_clear()
with open(out, "w") as f:
    json.dump(seen, f)
