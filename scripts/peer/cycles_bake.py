"""Bake a glTF scene's lightmap with Blender Cycles on lightmapd's texel grid.

Run inside Blender (3.4.1, Debian's package), headless:

    blender -b --factory-startup --python scripts/peer/cycles_bake.py -- \
        SCENE.glb OUT_DIR --resolution 64 --samples 64,256,1024 --seeds 1,2 --threads 2

For every (samples, seed) it writes OUT_DIR/cycles_<samples>_s<seed>.npy, a float32
array H x W x 4 (R, G, B, coverage) whose row 0 is the lightmap's row 0 in
lightmapd's convention (docs/conventions.md: v grows downward, as in glTF), and
OUT_DIR/cycles_times.json with the seconds of each `bpy.ops.object.bake` call.

What is baked, to match lightmapd's `path` (docs/peers.md):
- the UV map made from glTF TEXCOORD_1 (the importer's second UV map; the names are
  printed) is made active, so the bake lands on the same texels;
- bake type DIFFUSE, pass filter direct + indirect, colour OFF: the light the diffuse
  closure receives without the surface's albedo, i.e. irradiance / pi;
- every material is replaced by a Lambertian Diffuse BSDF (roughness 0) of the glTF
  baseColorFactor (bounded to 0.999 as lightmapd does) plus an Emission of
  emissiveFactor x KHR_materials_emissive_strength; single-sided materials reflect and
  emit nothing on their back faces (a black diffuse there), as lightmapd treats them;
- world black (or a uniform `--sky r,g,b` over the whole sphere: lightmapd's default
  `upper` sky is not reproduced, so use scenes without sky or with `--sky-hemisphere full`);
- CPU device, fixed thread count, adaptive sampling off, no denoising, no clamping,
  1024 bounces of every kind, margin 0;
- the objects are joined into one before baking (Blender's bake operator runs Cycles
  once per selected object, which costs ~0.1 s an object; `--no-join` keeps them).

Limits: base colour / emissive textures, alpha, punctual lights and the sun are not
translated (the script stops on a material with a texture); Cycles jitters each sample
over the texel's footprint (clamped into the triangle) while lightmapd samples the
surface point at the texel centre, so the two differ by the texel-area filtering where
irradiance curves within a texel (edges, corners, penumbrae); docs/peers.md measures
it and compares on interior texels.
"""

import argparse
import json
import os
import struct
import sys
import time

import bpy
import numpy as np

ALBEDO_BOUND = 0.999

# Debian's Blender 3.4.1 glTF importer still uses the aliases NumPy 1.24 removed
# (`np.bool` in set_poly_smoothing): put them back for the import.
for _alias, _type in (("bool", bool), ("int", int), ("float", float), ("object", object)):
    if not hasattr(np, _alias) or _alias == "bool":
        try:
            getattr(np, _alias)
        except AttributeError:
            setattr(np, _alias, _type)


def parse_args():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    p = argparse.ArgumentParser()
    p.add_argument("scene")
    p.add_argument("out")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--samples", default="64,256,1024")
    p.add_argument("--seeds", default="1,2")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--sky", default=None, help="uniform sky radiance r,g,b (whole sphere)")
    p.add_argument("--no-join", action="store_true",
                   help="bake the glTF's objects as imported (Blender bakes one object at a time)")
    return p.parse_args(argv)


def gltf_json(path):
    with open(path, "rb") as f:
        data = f.read()
    if data[:4] != b"glTF":
        with open(path) as f:
            return json.load(f)
    n = struct.unpack("<I", data[12:16])[0]
    return json.loads(data[20:20 + n])


def build_material(mat, gm):
    pbr = gm.get("pbrMetallicRoughness", {})
    if "baseColorTexture" in pbr or "emissiveTexture" in gm:
        raise SystemExit(f"material {gm.get('name')}: textures are not translated by this script")
    base = [min(ALBEDO_BOUND, c) for c in pbr.get("baseColorFactor", [0.8, 0.8, 0.8, 1.0])[:3]]
    strength = gm.get("extensions", {}).get("KHR_materials_emissive_strength", {}).get("emissiveStrength", 1.0)
    emissive = [c * strength for c in gm.get("emissiveFactor", [0.0, 0.0, 0.0])]
    double = gm.get("doubleSided", False)

    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    diff = nt.nodes.new("ShaderNodeBsdfDiffuse")
    diff.inputs["Color"].default_value = (*base, 1.0)
    diff.inputs["Roughness"].default_value = 0.0
    front = diff.outputs["BSDF"]
    if max(emissive) > 0.0:
        em = nt.nodes.new("ShaderNodeEmission")
        em.inputs["Color"].default_value = (*emissive, 1.0)
        em.inputs["Strength"].default_value = 1.0
        add = nt.nodes.new("ShaderNodeAddShader")
        nt.links.new(diff.outputs["BSDF"], add.inputs[0])
        nt.links.new(em.outputs["Emission"], add.inputs[1])
        front = add.outputs["Shader"]
    if double:
        nt.links.new(front, out.inputs["Surface"])
    else:
        geo = nt.nodes.new("ShaderNodeNewGeometry")
        black = nt.nodes.new("ShaderNodeBsdfDiffuse")
        black.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        mix = nt.nodes.new("ShaderNodeMixShader")
        nt.links.new(geo.outputs["Backfacing"], mix.inputs["Fac"])
        nt.links.new(front, mix.inputs[1])
        nt.links.new(black.outputs["BSDF"], mix.inputs[2])
        nt.links.new(mix.outputs["Shader"], out.inputs["Surface"])
    return nt


def main():
    args = parse_args()
    os.makedirs(args.out, exist_ok=True)
    samples = [int(s) for s in args.samples.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    W = H = args.resolution

    bpy.ops.wm.read_factory_settings(use_empty=True)
    t0 = time.perf_counter()
    bpy.ops.import_scene.gltf(filepath=args.scene)
    print(f"PEER import {time.perf_counter() - t0:.2f} s")
    gj = gltf_json(args.scene)
    by_name = {m.get("name", f"material{i}"): m for i, m in enumerate(gj.get("materials", []))}
    if gj.get("extensions", {}).get("KHR_lights_punctual"):
        print("PEER warning: punctual lights are not translated")
    for obj in list(bpy.data.objects):
        if obj.type != "MESH":
            bpy.data.objects.remove(obj)  # cameras, importer-made lights

    img = bpy.data.images.new("lightmap", W, H, alpha=True, float_buffer=True)
    img.colorspace_settings.name = "Linear"

    meshes = [o for o in bpy.data.objects if o.type == "MESH"]
    done = set()
    for obj in meshes:
        uvs = [uv.name for uv in obj.data.uv_layers]
        print(f"PEER object {obj.name!r} uv maps {uvs}")
        if len(uvs) < 2:
            raise SystemExit(f"{obj.name}: no TEXCOORD_1 (second UV map)")
        obj.data.uv_layers.active_index = 1  # glTF TEXCOORD_1
        for slot in obj.material_slots:
            mat = slot.material
            if mat is None or mat.name in done:
                continue
            gm = by_name.get(mat.name)
            if gm is None:
                raise SystemExit(f"material {mat.name!r} not found in the glTF")
            nt = build_material(mat, gm)
            tex = nt.nodes.new("ShaderNodeTexImage")
            tex.image = img
            for n in nt.nodes:
                n.select = False
            tex.select = True
            nt.nodes.active = tex
            done.add(mat.name)

    scene = bpy.context.scene
    world = bpy.data.worlds.new("peer")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    sky = [float(x) for x in args.sky.split(",")] if args.sky else [0.0, 0.0, 0.0]
    bg.inputs["Color"].default_value = (*sky, 1.0)
    bg.inputs["Strength"].default_value = 1.0
    scene.world = world

    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    scene.render.threads_mode = "FIXED"
    scene.render.threads = args.threads
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.max_bounces = 1024
    c.diffuse_bounces = 1024
    c.glossy_bounces = 1024
    c.transmission_bounces = 1024
    c.volume_bounces = 1024
    c.transparent_max_bounces = 1024
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.use_animated_seed = False
    b = scene.render.bake
    b.use_pass_direct = True
    b.use_pass_indirect = True
    b.use_pass_color = False
    b.margin = 0
    b.use_clear = True
    b.target = "IMAGE_TEXTURES"

    bpy.ops.object.select_all(action="DESELECT")
    for obj in meshes:
        obj.select_set(True)
    bpy.context.view_layer.objects.active = meshes[0]
    if not args.no_join and len(meshes) > 1:
        # One object: Blender's bake operator runs the engine once per selected object
        # (scene sync and set-up every time: 24 s for 16 samples on blocks-25k's 201
        # objects). Joining keeps every face's material and both UV maps, applies the
        # transforms, and changes no light transport.
        for obj in meshes:
            obj.data = obj.data.copy()  # the importer may share meshes between nodes
        bpy.ops.object.join()
        meshes = [bpy.context.view_layer.objects.active]
        meshes[0].data.uv_layers.active_index = 1
        print(f"PEER joined into one object: {len(meshes[0].data.polygons)} faces, "
              f"uv maps {[uv.name for uv in meshes[0].data.uv_layers]}, active {meshes[0].data.uv_layers.active.name}")

    print(f"PEER cycles settings: device {c.device}, threads {scene.render.threads}, "
          f"sampling {c.sampling_pattern}, light threshold {c.light_sampling_threshold:g}, "
          f"bounces {c.max_bounces}, clamp {c.sample_clamp_direct:g}/{c.sample_clamp_indirect:g}, "
          f"adaptive {c.use_adaptive_sampling}, denoise {c.use_denoising}, margin {b.margin}")
    times = []
    for n in samples:
        for seed in seeds:
            c.samples = n
            c.seed = seed
            t0 = time.perf_counter()
            bpy.ops.object.bake(type="DIFFUSE", pass_filter={"DIRECT", "INDIRECT"}, margin=0,
                                use_clear=True, target="IMAGE_TEXTURES")
            dt = time.perf_counter() - t0
            px = np.empty(W * H * 4, dtype=np.float32)
            img.pixels.foreach_get(px)
            # Blender's image row 0 is the bottom row (v = 0 after the importer's v -> 1 - v),
            # lightmapd's row 0 is glTF v = 0: flip.
            px = px.reshape(H, W, 4)[::-1].copy()
            np.save(os.path.join(args.out, f"cycles_{n}_s{seed}.npy"), px)
            times.append({"samples": n, "seed": seed, "seconds": dt})
            print(f"PEER cycles samples {n} seed {seed}: bake {dt:.2f} s, "
                  f"covered {(px[..., 3] > 0).sum()} texels, mean R {px[..., 0][px[..., 3] > 0].mean():.5f}")
            with open(os.path.join(args.out, "cycles_times.json"), "w") as f:
                json.dump({"blender": bpy.app.version_string, "threads": args.threads,
                           "resolution": W, "bakes": times}, f, indent=1)


main()
