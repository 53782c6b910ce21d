"""Run by Blender (tests/test_rig_import_fbx.py): an FBX of a face rig, made in Blender itself from an .npz
(neutral V x 3 and deltas m x V x 3 in metres, livecap's +Y up; triangles; names): mesh "Face" with one shape
key per shape, parented to an empty "Head" 5 cm up; Blender's FBX exporter writes it.

    blender -b --factory-startup --python tests/blender_fbx.py -- rig.npz out.fbx
"""

import sys

import bpy
import numpy as np

src, out = sys.argv[sys.argv.index("--") + 1:][:2]
bpy.ops.wm.read_factory_settings(use_empty=True)
z = np.load(src)
to_blender = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # +Y up -> Blender's +Z up
head = bpy.data.objects.new("Head", None)
head.location = (0.0, 0.0, 0.05)
neutral = z["neutral"] @ to_blender.T - np.array(head.location)
mesh = bpy.data.meshes.new("Face")
mesh.from_pydata(neutral.tolist(), [], z["triangles"].tolist())
face = bpy.data.objects.new("Face", mesh)
face.parent = head
for obj in (head, face):
    bpy.context.scene.collection.objects.link(obj)
face.shape_key_add(name="Basis")
for name, delta in zip(z["names"], z["deltas"], strict=True):
    key = face.shape_key_add(name=str(name))
    key.data.foreach_set("co", (neutral + delta @ to_blender.T).astype(np.float32).ravel())
bpy.ops.export_scene.fbx(filepath=out, object_types={"MESH", "EMPTY"}, add_leaf_bones=False)
