"""Open a keyshape .glb in Blender headless: count shape keys and keyframes, dump one evaluated frame.

Not a test (Blender is not a dependency). Usage, with Debian's blender 3.x (its Python needs numpy,
e.g. a folder holding a link to the venv's numpy on PYTHONPATH)::

    blender -b --python bench/blender_glb_check.py -- OUT.glb [FRAME OUT.npy]

Prints the mesh's vertex and shape-key counts, the F-curves and keyframes per curve of the
shape-key and head animations; with FRAME and OUT.npy, widens the shape-key slider ranges
(Blender 3.4's importer widens them from the first keyframe only), sets the scene to the
file's frame rate placement (30 fps) and saves the evaluated vertex positions (Blender Z-up).
"""
import sys

import bpy
import numpy as np

argv = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.context.scene.render.fps = 30
bpy.ops.import_scene.gltf(filepath=argv[0])
for ob in bpy.data.objects:
    if ob.type == "MESH":
        keys = ob.data.shape_keys
        names = [k.name for k in keys.key_blocks] if keys else []
        print("MESH", ob.name, "vertices", len(ob.data.vertices), "shape keys", len(names), names)
        act = keys.animation_data.action if keys and keys.animation_data else None
        if act:
            print("SHAPE-KEY ACTION", act.name, "fcurves", len(act.fcurves), "keyframes per fcurve",
                  sorted({len(fc.keyframe_points) for fc in act.fcurves}))
        if len(argv) == 3:
            for k in keys.key_blocks[1:]:
                k.slider_min, k.slider_max = -10.0, 10.0
            bpy.context.scene.frame_set(int(argv[1]))
            me = ob.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
            co = np.empty(len(me.vertices) * 3)
            me.vertices.foreach_get("co", co)
            np.save(argv[2], co.reshape(-1, 3))
            print("SAVED frame", argv[1], "to", argv[2])
    if ob.animation_data and ob.animation_data.action:
        act = ob.animation_data.action
        print("NODE ACTION", ob.name, sorted({fc.data_path for fc in act.fcurves}),
              "keyframes per fcurve", sorted({len(fc.keyframe_points) for fc in act.fcurves}))
