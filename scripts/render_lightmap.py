# Renders a one-page lightmap on its scene's geometry with Blender (headless, Cycles on the
# CPU): every surface emits the lightmap's value (irradiance / pi, DESIGN section 2) looked
# up at TEXCOORD_1, so what shows is the baked light alone, as a level editor would see it
# on white surfaces. The camera looks along the scene's +Y (glTF -Z) at its bounds.
# Used to look at bakes in rounds against single bakes (docs/scaling.md).
#
#   blender -b -P scripts/render_lightmap.py -- SCENE.glb LIGHTMAP OUT.png [EYE AT]
#
# LIGHTMAP: one EXR for every mesh, or the folder a bake wrote (`-o DIR` with the scene's
# `--write-gltf`), whose nodes name their page and instance rectangle in
# `extras.lightmap` (docs/conventions.md): instanced meshes then read each their own
# rectangle, on their own page.
#
# EXPOSURE=-3 (stops) in the environment darkens the picture for sunlit bakes.
#
# EYE and AT (optional, glTF coordinates, "x,y,z"): a camera at EYE looking at AT, for
# looking at a room from inside (the default camera frames the scene from outside).
#
# Limits: no tone mapping beyond Blender's
# "Standard" view; Blender's glTF importer of Debian bookworm (3.4) needs numpy's old
# `np.bool` alias, restored here.
import numpy as _np
if not hasattr(_np, "bool"): _np.bool = bool
import bpy, sys, os, math, mathutils
argv = sys.argv[sys.argv.index("--")+1:]
glb, exr, out = argv[:3]
# glTF is +Y up, Blender +Z up: the importer maps (x, y, z) to (x, -z, y).
def from_gltf(text):
    x, y, z = (float(v) for v in text.split(","))
    return mathutils.Vector((x, -z, y))
view = (from_gltf(argv[3]), from_gltf(argv[4])) if len(argv) >= 5 else None
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=glb)
# LIGHTMAP is one EXR, or a bake's output folder: then each node reads the page its
# `extras.lightmap.file` names (docs/conventions.md), through its `scale_offset`.
images = {}
def image(path):
    if path not in images:
        images[path] = bpy.data.images.load(path)
        images[path].colorspace_settings.name = 'Non-Color'
    return images[path]
for ob in [o for o in bpy.data.objects if o.type == 'MESH']:
    uvs = ob.data.uv_layers
    lm = uvs[1].name if len(uvs) > 1 else uvs[0].name
    placed = ob.get("lightmap")
    path = exr
    if os.path.isdir(exr):
        path = os.path.join(exr, placed["file"] if placed is not None else "lightmap-0.exr")
    m = bpy.data.materials.new("lm_" + ob.name); m.use_nodes = True
    nt = m.node_tree; nt.nodes.clear()
    uv = nt.nodes.new('ShaderNodeUVMap'); uv.uv_map = lm
    tex = nt.nodes.new('ShaderNodeTexImage'); tex.image = image(path); tex.interpolation = 'Linear'
    em = nt.nodes.new('ShaderNodeEmission')
    outn = nt.nodes.new('ShaderNodeOutputMaterial')
    if placed is not None:
        # The instance's rectangle: page UV = TEXCOORD_1 * (sx, sy) + (ox, oy) in glTF's
        # UV space; Blender's importer flips v (v_b = 1 - v), so v_b * sy + 1 - sy - oy.
        sx, sy, ox, oy = (float(v) for v in placed["scale_offset"])
        mp = nt.nodes.new('ShaderNodeMapping')
        mp.inputs['Scale'].default_value = (sx, sy, 1.0)
        mp.inputs['Location'].default_value = (ox, 1.0 - sy - oy, 0.0)
        nt.links.new(uv.outputs['UV'], mp.inputs['Vector'])
        nt.links.new(mp.outputs['Vector'], tex.inputs['Vector'])
    else:
        nt.links.new(uv.outputs['UV'], tex.inputs['Vector'])
    nt.links.new(tex.outputs['Color'], em.inputs['Color'])
    nt.links.new(em.outputs['Emission'], outn.inputs['Surface'])
    # Instances share their mesh data: the material goes on the object, not the mesh.
    ob.data.materials.clear(); ob.data.materials.append(m)
    ob.material_slots[0].link = 'OBJECT'; ob.material_slots[0].material = m
# camera: look into the box along -z from the bounds' front
mins = mathutils.Vector((1e9,)*3); maxs = mathutils.Vector((-1e9,)*3)
for ob in bpy.data.objects:
    if ob.type != 'MESH': continue
    for c in ob.bound_box:
        w = ob.matrix_world @ mathutils.Vector(c)
        mins = mathutils.Vector(map(min, mins, w)); maxs = mathutils.Vector(map(max, maxs, w))
ctr = (mins+maxs)/2; size = max(maxs-mins)
cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
bpy.context.scene.collection.objects.link(cam)
cam.location = ctr + mathutils.Vector((0, -0.0, 0)) + mathutils.Vector((0,0,0))
# glTF +Z forward becomes Blender -Y: put camera in front (-Y side) looking +Y
cam.location = mathutils.Vector((ctr.x, mins.y - 1.6*size, ctr.z))
cam.rotation_euler = (math.radians(90), 0, 0)
cam.data.lens = 35
if view is not None:
    eye, at = view
    cam.location = eye
    cam.rotation_euler = (at - eye).to_track_quat('-Z', 'Y').to_euler()
    cam.data.lens = 18
sc = bpy.context.scene; sc.camera = cam
sc.render.engine = 'CYCLES'; sc.cycles.samples = 8; sc.cycles.device = 'CPU'; sc.cycles.use_denoising = False
sc.view_settings.view_transform = 'Standard'
# EXPOSURE (stops, default 0) in the environment: a sunlit level's lightmap is well above 1.
sc.view_settings.exposure = float(os.environ.get('EXPOSURE', '0'))
sc.render.resolution_x = 480; sc.render.resolution_y = 480
sc.render.filepath = out
bpy.ops.render.render(write_still=True)
