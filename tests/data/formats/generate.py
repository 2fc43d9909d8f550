import json, math, os, struct, zlib

def norm(v):
    l = math.sqrt(sum(x*x for x in v)); return [x/l for x in v]
def cross(a, b):
    return [a[1]*b[2]-a[2]*b[1], a[2]*b[0]-a[0]*b[2], a[0]*b[1]-a[1]*b[0]]
def look_at(eye, target=(0,0,0), up=(0,0,1)):
    # OpenGL camera: -z looks at the target, +y up, +x right.  Columns = camera axes in world.
    z = norm([eye[i]-target[i] for i in range(3)])
    x = norm(cross(up, z))
    y = cross(z, x)
    return [[x[0], y[0], z[0], eye[0]], [x[1], y[1], z[1], eye[1]], [x[2], y[2], z[2], eye[2]], [0.0, 0.0, 0.0, 1.0]]
def sphere(r, az, el):
    return [r*math.cos(el)*math.cos(az), r*math.cos(el)*math.sin(az), r*math.sin(el)]
def r17(m):
    return [[float("%.17g" % v) for v in row] for row in m]

def png_rgba(path, w, h, seed):
    rows = b""
    for y in range(h):
        rows += b"\x00" + bytes(((x*31 + y*17 + seed*7 + c*50) % 256) if c < 3 else (255 if (x+y) % 3 else 0) for x in range(w) for c in range(4))
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xffffffff)
    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0)) + chunk(b"IDAT", zlib.compress(rows, 9)) + chunk(b"IEND", b"")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    open(path, "wb").write(data)

# Blender NeRF synthetic layout: camera_angle_x only, extension-less paths, no w/h.
base = "nerf_synthetic"
angle = 0.6911112070083618
for split, n, r in (("train", 3, 4.031), ("val", 1, 4.031), ("test", 2, 4.031)):
    frames = []
    for i in range(n):
        az = 0.7 + 1.9*i + (0.3 if split == "test" else 0.0)
        el = 0.35 + 0.2*i
        frames.append({"file_path": "./%s/r_%d" % (split, i), "rotation": 0.012566370614359171,
                       "transform_matrix": r17(look_at(sphere(r, az, el)))})
        png_rgba(os.path.join(base, split, "r_%d.png" % i), 8, 6, i + (10 if split == "test" else 0))
    json.dump({"camera_angle_x": angle, "frames": frames}, open(os.path.join(base, "transforms_%s.json" % split), "w"), indent=4)

# instant-ngp capture converted from COLMAP by scripts/colmap2nerf.py (images need not exist).
ngp = {"camera_angle_x": 1.2548098419745496, "camera_angle_y": 0.7685011006233613,
       "fl_x": 1375.5210563891232, "fl_y": 1374.4929911283916,
       "k1": 0.005716366767137553, "k2": -0.014398416219520378, "k3": 0, "k4": 0,
       "p1": -0.0003135620560546155, "p2": 0.0004148622683003036, "is_fisheye": False,
       "cx": 964.2156614587127, "cy": 541.1364584958453, "w": 1920.0, "h": 1080.0,
       "aabb_scale": 16, "frames": []}
for i in range(4):
    m = look_at(sphere(3.2, 0.4 + 0.8*i, 0.25), target=(0.05, -0.02, 0.1))
    ngp["frames"].append({"file_path": "./images/%04d.jpg" % (i + 1), "sharpness": 31.75 + 3.1*i,
                          "transform_matrix": r17(m)})
json.dump(ngp, open("ngp_capture/transforms.json", "w") if os.path.isdir("ngp_capture") else (os.makedirs("ngp_capture") or open("ngp_capture/transforms.json", "w")), indent=2)
