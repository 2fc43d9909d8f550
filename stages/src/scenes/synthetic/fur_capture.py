"""Renders a furry capture with Blender's own hair, for fure's capture pipeline.

    blender -b --factory-startup -P fur_capture.py -- SKIN.obj OUT_DIR [options]

SKIN.obj is a labelled mesh (one OBJ group per part, Y up, as fure's synthetic `scene.skin`).
Blender grows particle hair on it (none on the parts named by --bare), renders RGBA views around
it with Cycles, and writes, in the mesh's own frame and units:

    OUT_DIR/views/transforms.json, transforms_test.json, train/NNN.png, test/NNN.png
    OUT_DIR/gt/strands.hair        the hair as rendered (Cem Yuksel's .hair: segments + points)

(`--hair-only`: the hair alone, no views.) The `synthetic_scene` stage runs this script for
`renderer = "blender"` (scenes::synthetic::blender).

The hair model (Blender's particle hair, Cycles' Principled Hair BSDF), the renderer (Cycles,
Filmic view transform) and the camera convention are Blender's, not fure's: a capture made by
other software. Blender 3.4's Python has no numpy; only the standard library is used.
"""
import argparse
import json
import math
import os
import struct
import sys

import bpy
from mathutils import Matrix, Vector

argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
ap = argparse.ArgumentParser()
ap.add_argument("skin")
ap.add_argument("out")
ap.add_argument("--views", type=int, default=24)
ap.add_argument("--test-views", type=int, default=2)
ap.add_argument("--resolution", type=int, default=128)
ap.add_argument("--hairs", type=int, default=20000)
ap.add_argument("--length", type=float, default=0.04, help="typical hair length, mesh units")
ap.add_argument("--radius", type=float, default=0.004, help="hair root radius, mesh units")
ap.add_argument("--rise", type=float, default=0.6,
                help="how much the hair leaves along the normal against lying toward -x, -y")
ap.add_argument("--samples", type=int, default=16)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--bare", default="eyes,nose,pads")
ap.add_argument("--hair-only", action="store_true", help="write gt/strands.hair, render nothing")
args = ap.parse_args(argv)

bpy.ops.wm.read_factory_settings(use_empty=True)
# The OBJ is read here rather than by Blender's importer, so the mesh keeps the file's frame
# (Blender's world frame is the mesh's: Y up, gravity -Y) and each face keeps its `g` group.
verts, faces, face_group = [], [], []
group = ""
with open(args.skin) as f:
    for line in f:
        w = line.split()
        if not w:
            continue
        if w[0] == "v":
            verts.append(tuple(float(x) for x in w[1:4]))
        elif w[0] == "g":
            group = w[1] if len(w) > 1 else ""
        elif w[0] == "f":
            faces.append(tuple(int(x.split("/")[0]) - 1 for x in w[1:]))
            face_group.append(group)
me = bpy.data.meshes.new("skin")
me.from_pydata(verts, [], faces)
me.update()
ob = bpy.data.objects.new("skin", me)
bpy.context.scene.collection.objects.link(ob)
bpy.context.view_layer.objects.active = ob
bare = {b.strip() for b in args.bare.split(",") if b.strip()}
fur = ob.vertex_groups.new(name="fur")
# Weight 1 on the vertices no bare face touches: Blender interpolates the density over a face,
# so a bare face whose corners all border fur would otherwise grow hair.
bare_verts = {i for face, g in zip(faces, face_group) if g in bare for i in face}
fur.add(sorted({i for face, g in zip(faces, face_group) if g not in bare for i in face} - bare_verts),
        1.0, "REPLACE")

skin = bpy.data.materials.new("skin")
skin.use_nodes = True
skin.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.25, 0.12, 0.06, 1.0)
hair = bpy.data.materials.new("hair")
hair.use_nodes = True
nt = hair.node_tree
for n in list(nt.nodes):
    nt.nodes.remove(n)
bsdf = nt.nodes.new("ShaderNodeBsdfHairPrincipled")
bsdf.parametrization = "MELANIN"
bsdf.inputs["Melanin"].default_value = 0.55
bsdf.inputs["Melanin Redness"].default_value = 0.8
nt.links.new(bsdf.outputs[0], nt.nodes.new("ShaderNodeOutputMaterial").inputs["Surface"])
me.materials.append(skin)
me.materials.append(hair)

ob.modifiers.new("hair", "PARTICLE_SYSTEM")
psys = ob.particle_systems[0]
psys.seed = args.seed
psys.vertex_group_density = "fur"
ps = psys.settings
ps.type = "HAIR"
ps.count = args.hairs
ps.hair_step = 5
ps.emit_from = "FACE"
ps.distribution = "RAND"
ps.use_even_distribution = True
# Advanced hair: each strand leaves along its emission velocity, four times as long as the
# velocity, so fur that lies down toward the tail (-x) and the ground (-y) is a velocity along
# rise n + (-0.5, -0.4, 0) (rise 0.6: about 40 degrees over the skin).
# The velocity is divided by its length where the skin's normal is square to the combing
# direction, so the hair there is `--length` long.
ps.use_advanced_hair = True
v = args.length / 4 / math.sqrt(args.rise ** 2 + 0.5 ** 2 + 0.4 ** 2)
ps.normal_factor = args.rise * v
ps.object_align_factor = (-0.5 * v, -0.4 * v, 0.0)
ps.factor_random = 0.1 * v
ps.child_type = "NONE"
ps.display_step = 3
ps.render_step = 3
ps.root_radius = 1.0
ps.tip_radius = 0.3
ps.radius_scale = args.radius
ps.material = 2

sc = bpy.context.scene
sc.render.engine = "CYCLES"
sc.cycles.device = "CPU"
sc.cycles.samples = args.samples
sc.cycles.use_denoising = False
sc.cycles.seed = args.seed
sc.render.resolution_x = sc.render.resolution_y = args.resolution
sc.render.resolution_percentage = 100
sc.render.film_transparent = True
sc.render.image_settings.file_format = "PNG"
sc.render.image_settings.color_mode = "RGBA"
world = bpy.data.worlds.new("world")
world.color = (0.35, 0.35, 0.35)
sc.world = world
sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
sun.data.energy = 3.0
sun.rotation_euler = (math.radians(-60), math.radians(20), 0.0)
sc.collection.objects.link(sun)

# Cameras on a sphere about the mesh's bounding-box centre, framing its bounding sphere grown by
# the hair in a 40-degree field of view: training views on a Fibonacci spiral over elevations
# -30..70 degrees, held-out views on a ring at 10 degrees.
lo = Vector([min(v[i] for v in verts) for i in range(3)])
hi = Vector([max(v[i] for v in verts) for i in range(3)])
centre = (lo + hi) / 2
fov = math.radians(40.0)
dist = ((hi - lo).length / 2 + args.length) / math.sin(fov / 2)
cam_data = bpy.data.cameras.new("camera")
cam_data.angle = fov
cam_data.sensor_fit = "HORIZONTAL"
cam = bpy.data.objects.new("camera", cam_data)
sc.collection.objects.link(cam)
sc.camera = cam


def look_at(position):
    forward = (centre - position).normalized()
    right = forward.cross(Vector((0.0, 1.0, 0.0))).normalized()
    up = right.cross(forward)
    # Blender's camera looks down its -z with +y up: the NeRF / OpenGL convention.
    return Matrix.Translation(position) @ Matrix((right, up, -forward)).transposed().to_4x4()


def direction(elev, azim):
    return Vector((math.cos(elev) * math.cos(azim), math.sin(elev), math.cos(elev) * math.sin(azim)))


def render(split, dirs, name):
    frames = []
    os.makedirs(os.path.join(args.out, "views", split), exist_ok=True)
    for i, d in enumerate(dirs):
        cam.matrix_world = look_at(centre + d * dist)
        rel = f"{split}/{i:03d}.png"
        sc.render.filepath = os.path.join(args.out, "views", rel)
        bpy.ops.render.render(write_still=True)
        frames.append({"file_path": rel, "transform_matrix": [list(r) for r in cam.matrix_world]})
    meta = {"camera_angle_x": fov, "w": args.resolution, "h": args.resolution, "frames": frames}
    with open(os.path.join(args.out, "views", name), "w") as f:
        json.dump(meta, f)


golden = math.pi * (3.0 - math.sqrt(5.0))
lo_s, hi_s = math.sin(math.radians(-30)), math.sin(math.radians(70))
train = [direction(math.asin(lo_s + (hi_s - lo_s) * (i + 0.5) / args.views), golden * i)
         for i in range(args.views)]
test = [direction(math.radians(10), 2 * math.pi * (k + 0.5) / max(args.test_views, 1))
        for k in range(args.test_views)]
if not args.hair_only:
    render("train", train, "transforms.json")
    render("test", test, "transforms_test.json")

# The hair as rendered: `co_hair` gives each strand's world-space points at the render steps.
ev = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
epsys = ev.particle_systems[0]
steps = 2 ** ps.render_step
strands = [[epsys.co_hair(ev, particle_no=i, step=k) for k in range(steps + 1)]
           for i in range(len(epsys.particles))]
os.makedirs(os.path.join(args.out, "gt"), exist_ok=True)
npts = sum(len(s) for s in strands)
with open(os.path.join(args.out, "gt", "strands.hair"), "wb") as f:
    # Header: "HAIR", strands, points, flags (bit 0 segments, bit 1 points), default segments,
    # default thickness, transparency and colour, 88 bytes of information.
    f.write(b"HAIR" + struct.pack("<IIII", len(strands), npts, 0b11, steps))
    f.write(struct.pack("<5f", 2 * args.radius, 1.0, 0.5, 0.3, 0.1))
    f.write(b"fure tests/data/blender/fur_capture.py".ljust(88, b"\0"))
    f.write(struct.pack(f"<{len(strands)}H", *[len(s) - 1 for s in strands]))
    for s in strands:
        for p in s:
            f.write(struct.pack("<3f", p.x, p.y, p.z))
views = 0 if args.hair_only else len(train) + len(test)
print(f"fur_capture: Blender {bpy.app.version_string}, {len(strands)} strands, {npts} points, {views} views")
