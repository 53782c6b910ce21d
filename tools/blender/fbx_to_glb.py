"""FBX (or any file Blender imports: .fbx, .dae, .abc, .blend) to a GLB with its shape keys as morph targets.

    blender -b --factory-startup --python tools/blender/fbx_to_glb.py -- IN.fbx OUT.glb

Then ``livecap rig import OUT.glb --out rig.npz``. Blender's FBX importer applies the file's unit scale
(FBX is centimetres unless it says otherwise) and its axes; the glTF exporter writes metres, +Y up, one
morph target per shape key, named in ``extras.targetNames``. Run with Blender's own Python, not livecap's.
"""

import sys
from pathlib import Path

import bpy

src, out = sys.argv[sys.argv.index("--") + 1:][:2]
bpy.ops.wm.read_factory_settings(use_empty=True)
suffix = Path(src).suffix.lower()
if suffix == ".fbx":
    bpy.ops.import_scene.fbx(filepath=src)
elif suffix == ".dae":
    bpy.ops.wm.collada_import(filepath=src)
elif suffix == ".abc":
    bpy.ops.wm.alembic_import(filepath=src)
elif suffix == ".blend":
    bpy.ops.wm.open_mainfile(filepath=src)
else:
    sys.exit(f"{src}: not a file this script converts (.fbx, .dae, .abc, .blend)")
keys = [o.name for o in bpy.data.objects if o.type == "MESH" and o.data.shape_keys]
if not keys:
    sys.exit(f"{src}: no mesh with shape keys")
bpy.ops.export_scene.gltf(filepath=out, export_format="GLB", export_morph=True, export_morph_normal=False,
                          export_apply=False, export_animations=False)
print(f"{out}: meshes with shape keys: {', '.join(keys)}")
