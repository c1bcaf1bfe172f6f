# Renders a one-page lightmap on its scene's geometry with Blender (headless, Cycles on the
# CPU): every surface emits the lightmap's value (irradiance / pi, DESIGN section 2) looked
# up at TEXCOORD_1, so what shows is the baked light alone, as a level editor would see it
# on white surfaces. The camera looks along the scene's +Y (glTF -Z) at its bounds.
# Used to look at bakes in rounds against single bakes (docs/scaling.md).
#
#   blender -b -P scripts/render_lightmap.py -- SCENE.glb LIGHTMAP.exr OUT.png [EYE AT]
#
# EYE and AT (optional, glTF coordinates, "x,y,z"): a camera at EYE looking at AT, for
# looking at a room from inside (the default camera frames the scene from outside).
#
# Limits: one page (every mesh samples the same EXR); no tone mapping beyond Blender's
# "Standard" view; Blender's glTF importer of Debian bookworm (3.4) needs numpy's old
# `np.bool` alias, restored here.
import numpy as _np
if not hasattr(_np, "bool"): _np.bool = bool
import bpy, sys, math, mathutils
argv = sys.argv[sys.argv.index("--")+1:]
glb, exr, out = argv[:3]
# glTF is +Y up, Blender +Z up: the importer maps (x, y, z) to (x, -z, y).
def from_gltf(text):
    x, y, z = (float(v) for v in text.split(","))
    return mathutils.Vector((x, -z, y))
view = (from_gltf(argv[3]), from_gltf(argv[4])) if len(argv) >= 5 else None
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=glb)
img = bpy.data.images.load(exr)
img.colorspace_settings.name = 'Non-Color'
mats = {}
for ob in bpy.data.objects:
    if ob.type != 'MESH': continue
    uvs = ob.data.uv_layers
    lm = uvs[1].name if len(uvs) > 1 else uvs[0].name
    m = bpy.data.materials.new("lm_" + ob.name); m.use_nodes = True
    nt = m.node_tree; nt.nodes.clear()
    uv = nt.nodes.new('ShaderNodeUVMap'); uv.uv_map = lm
    tex = nt.nodes.new('ShaderNodeTexImage'); tex.image = img; tex.interpolation = 'Linear'
    em = nt.nodes.new('ShaderNodeEmission')
    outn = nt.nodes.new('ShaderNodeOutputMaterial')
    nt.links.new(uv.outputs['UV'], tex.inputs['Vector'])
    nt.links.new(tex.outputs['Color'], em.inputs['Color'])
    nt.links.new(em.outputs['Emission'], outn.inputs['Surface'])
    ob.data.materials.clear(); ob.data.materials.append(m)
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
sc.render.resolution_x = 480; sc.render.resolution_y = 480
sc.render.filepath = out
bpy.ops.render.render(write_still=True)
