"""Blender script: key a mesh's shape keys from a keyshape curves CSV (``frame,time,<shape>,...``).

Run inside Blender (Text Editor, or headless)::

    blender scene.blend --python blender_import_curves.py -- curves.csv [OBJECT] [--fps 30]
    blender -b --python blender_import_curves.py -- curves.csv --glb take.glb --save out.blend

``curves.csv`` is what ``keyshape retarget WEIGHTS.csv --poses POSES.json --rig RIG -o curves.csv``
writes (a Live Link Face CSV is read too: its ``Timecode`` rows become frames 0, 1, ...).
Every column whose name is a shape key of OBJECT (default: the active object, else the first
mesh with shape keys) is keyed at every frame (``value`` of the shape key, linear
interpolation); the slider range is widened to the values met. Unknown columns are listed
and skipped. The scene's frame range is set to the CSV's frames and the frame rate to
``--fps`` (default: the scene extras ``fps`` of an imported keyshape .glb, else the CSV's
``time`` column, else 30).
With ``--glb FILE`` the .glb is imported first (Blender's glTF importer) and its scene
extras ``frame_start``/``frame_end``/``fps`` set the range. Needs no package beyond Blender.
"""
import csv
import sys

import bpy


def _args():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    opts = {"csv": None, "object": None, "fps": None, "glb": None, "save": None}
    it = iter(argv)
    for a in it:
        if a in ("--fps", "--glb", "--save"):
            opts[a[2:]] = next(it)
        elif opts["csv"] is None:
            opts["csv"] = a
        else:
            opts["object"] = a
    if not opts["csv"]:
        raise SystemExit("usage: blender --python blender_import_curves.py -- curves.csv [OBJECT] [--fps F] "
                         "[--glb take.glb] [--save out.blend]")
    return opts


def read_curves(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    head = [h.strip() for h in rows[0]]
    body = [r for r in rows[1:] if r and any(c.strip() for c in r)]
    fps = None
    if head[0] == "frame":
        frames = [int(float(r[0])) for r in body]
        first = 2 if head[1:2] == ["time"] else 1               # frame,time,<shape>,...
        if first == 2 and len(body) > 1 and float(body[-1][1]) > float(body[0][1]):
            fps = (frames[-1] - frames[0]) / (float(body[-1][1]) - float(body[0][1]))
        cols = head[first:]
        values = [[float(x) for x in r[first:]] for r in body]
    elif head[0] == "Timecode":                                 # Live Link Face: skip BlendShapeCount
        frames = list(range(len(body)))
        cols = head[2:]
        values = [[float(x) for x in r[2:]] for r in body]
    else:
        raise SystemExit(f"{path}: expected a 'frame,...' or Live Link 'Timecode,...' header")
    return frames, cols, values, fps


def find_object(name):
    if name:
        return bpy.data.objects[name]
    ob = bpy.context.view_layer.objects.active
    if ob is not None and ob.type == "MESH" and ob.data.shape_keys:
        return ob
    for ob in bpy.data.objects:
        if ob.type == "MESH" and ob.data.shape_keys:
            return ob
    raise SystemExit("no mesh with shape keys in the scene")


def main():
    o = _args()
    scene = bpy.context.scene
    fps = None
    if o["glb"]:
        bpy.ops.import_scene.gltf(filepath=o["glb"])
        ext = {k: scene[k] for k in ("fps", "frame_start", "frame_end") if k in scene.keys()}
        fps = ext.get("fps")
        if "frame_start" in ext:
            scene.frame_start, scene.frame_end = int(ext["frame_start"]), int(ext["frame_end"])
    frames, cols, values, csv_fps = read_curves(o["csv"])
    fps = float(o["fps"] or fps or csv_fps or 30)
    scene.render.fps, scene.render.fps_base = round(fps), round(fps) / fps
    ob = find_object(o["object"])
    keys = ob.data.shape_keys.key_blocks
    used, skipped = [], []
    for j, c in enumerate(cols):
        kb = keys.get(c)
        if kb is None:
            skipped.append(c)
            continue
        col = [v[j] for v in values]
        kb.slider_min, kb.slider_max = min(0.0, min(col)), max(1.0, max(col))
        for fr, v in zip(frames, col):
            kb.value = v
            kb.keyframe_insert("value", frame=fr)
        used.append(c)
    act = ob.data.shape_keys.animation_data.action if ob.data.shape_keys.animation_data else None
    if act:
        for fc in act.fcurves:
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"
    scene.frame_start, scene.frame_end = min(frames), max(frames)
    print(f"keyed {len(used)} shape keys of {ob.name} over frames {min(frames)}-{max(frames)} at {fps:g} fps; "
          f"skipped {len(skipped)} columns without a shape key: {', '.join(skipped[:10])}")
    if o["save"]:
        bpy.ops.wm.save_as_mainfile(filepath=o["save"])


main()
