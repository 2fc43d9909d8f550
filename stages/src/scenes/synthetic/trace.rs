//! The ground-truth renderer: ray-traced skin and strands with Kajiya-Kay hair shading.
//!
//! It shares no code with the differentiable Gaussian renderer the optimiser uses, so errors
//! of one cannot hide in the other. One BVH ([`super::bvh`]) holds the skin triangles and every
//! strand segment. A segment is a thin tapered tube of radius `w/2` at the root falling linearly
//! to 30 % at the tip; its intersection is the closest approach of the ray and the segment axis
//! (accepted when nearer than the local radius, hit distance moved to the tube's front surface),
//! which is exact enough for tubes about a pixel wide. Triangles use Moeller-Trumbore, two-sided.
//!
//! Shading is fixed in world space (a real capture's lights do not move with the camera): a key
//! light from above-front, a fill light from the other side, and ambient. Strands use Kajiya-Kay
//! (diffuse `sin(T, L)`, specular `(sin(T,L) sin(T,E) - cos(T,L) cos(T,E))^40`, weak and
//! white) times a root-to-tip occlusion ramp `0.45 + 0.55 s^0.7` that stands in for
//! self-shadowing inside the coat; the skin uses Lambert, eyes get a Blinn-Phong highlight. No
//! cast shadows. Colours are computed in linear RGB, averaged over the supersamples, and encoded
//! to sRGB for the PNGs.
//!
//! Antialiasing: `ss x ss` stratified jittered samples per pixel; the jitter of each sample comes
//! from a hash of (seed, view, pixel, sample), so any row order gives the same image. Rows are
//! rendered in parallel with rayon and collected in row order.

use glam::Vec3;
use rayon::prelude::*;

use super::bvh::{Aabb, Bvh};
use super::fur::mix;
use crate::data::camera::Camera;
use crate::data::image::ImageF32;
use crate::data::mesh::Mesh;
use crate::data::strands::Strands;

#[derive(Debug, Clone, Copy)]
struct Seg {
    p0: Vec3,
    r0: f32,
    p1: Vec3,
    r1: f32,
    strand: u32,
    /// Arc parameter (0 root .. 1 tip) at p0 and p1.
    s0: f32,
    s1: f32,
}

/// Everything the tracer needs, built once per scene.
pub struct Scene {
    bvh: Bvh,
    verts: Vec<Vec3>,
    normals: Vec<Vec3>,
    vcolor: Vec<[f32; 3]>,
    shiny: Vec<bool>,
    tris: Vec<[u32; 3]>,
    segs: Vec<Seg>,
    strand_color: Vec<[f32; 3]>,
}

/// One rendered view.
pub struct Frame {
    /// RGBA, sRGB-encoded colour with straight (unpremultiplied) alpha = coverage.
    pub rgba: ImageF32,
    /// Fraction of samples whose first hit is a strand.
    pub fur: ImageF32,
    /// Mean view-axis depth of the covered samples (0 where nothing was hit).
    pub depth: ImageF32,
}

struct Light {
    dir: Vec3,
    intensity: f32,
}

fn lights() -> [Light; 2] {
    [
        Light {
            dir: Vec3::new(0.35, 1.0, 0.45).normalize(),
            intensity: 0.85,
        },
        Light {
            dir: Vec3::new(-0.6, 0.35, -0.55).normalize(),
            intensity: 0.35,
        },
    ]
}
const AMBIENT: f32 = 0.28;

/// Hit record: distance, primitive, and (barycentric u, v) or (segment parameter, 0).
#[derive(Debug, Clone, Copy)]
struct Hit {
    t: f32,
    prim: u32,
    u: f32,
    v: f32,
}

impl Scene {
    /// Builds the scene from the skin (with per-vertex colours; `shiny` marks vertices of
    /// glossy parts such as eyes) and the strands.
    pub fn new(mesh: &Mesh, vcolor: Vec<[f32; 3]>, shiny: Vec<bool>, strands: &Strands) -> Scene {
        let mut segs = Vec::with_capacity(strands.segment_count());
        for s in 0..strands.len() {
            let pts = strands.strand(s);
            let n = pts.len().saturating_sub(1).max(1) as f32;
            let r = 0.5 * strands.width.get(s).copied().unwrap_or(0.0);
            for (k, w) in pts.windows(2).enumerate() {
                let s0 = k as f32 / n;
                let s1 = (k + 1) as f32 / n;
                segs.push(Seg {
                    p0: w[0],
                    r0: r * (1.0 - 0.7 * s0),
                    p1: w[1],
                    r1: r * (1.0 - 0.7 * s1),
                    strand: s as u32,
                    s0,
                    s1,
                });
            }
        }
        let mut boxes = Vec::with_capacity(mesh.triangles.len() + segs.len());
        for t in &mesh.triangles {
            let mut b = Aabb::EMPTY;
            for &i in t {
                b.grow_point(mesh.positions[i as usize]);
            }
            boxes.push(b);
        }
        for s in &segs {
            let r = Vec3::splat(s.r0.max(s.r1));
            boxes.push(Aabb {
                lo: s.p0.min(s.p1) - r,
                hi: s.p0.max(s.p1) + r,
            });
        }
        Scene {
            bvh: Bvh::build(&boxes),
            verts: mesh.positions.clone(),
            normals: mesh.normals.clone(),
            vcolor,
            shiny,
            tris: mesh.triangles.clone(),
            segs,
            strand_color: strands.color.clone(),
        }
    }

    pub fn segment_count(&self) -> usize {
        self.segs.len()
    }

    #[inline]
    fn hit_tri(&self, i: usize, o: Vec3, d: Vec3, tmax: f32) -> Option<(f32, f32, f32)> {
        let [a, b, c] = self.tris[i].map(|k| self.verts[k as usize]);
        let e1 = b - a;
        let e2 = c - a;
        let p = d.cross(e2);
        let det = e1.dot(p);
        if det.abs() < 1e-12 {
            return None;
        }
        let inv = 1.0 / det;
        let s = o - a;
        let u = s.dot(p) * inv;
        if !(0.0..=1.0).contains(&u) {
            return None;
        }
        let q = s.cross(e1);
        let v = d.dot(q) * inv;
        if v < 0.0 || u + v > 1.0 {
            return None;
        }
        let t = e2.dot(q) * inv;
        (t > 1e-6 && t < tmax).then_some((t, u, v))
    }

    #[inline]
    fn hit_seg(&self, i: usize, o: Vec3, d: Vec3, tmax: f32) -> Option<(f32, f32)> {
        let s = &self.segs[i];
        let u = s.p1 - s.p0;
        let w = o - s.p0;
        let b = d.dot(u);
        let c = u.dot(u);
        let dd = d.dot(w);
        let e = u.dot(w);
        let den = c - b * b;
        let mut sp = if den > 1e-12 { (e - b * dd) / den } else { 0.0 };
        sp = sp.clamp(0.0, 1.0);
        let t = sp * b - dd;
        let diff = w + d * t - u * sp;
        let dist2 = diff.length_squared();
        let r = s.r0 + (s.r1 - s.r0) * sp;
        if dist2 >= r * r {
            return None;
        }
        let t = t - (r * r - dist2).sqrt();
        (t > 1e-6 && t < tmax).then_some((t, sp))
    }

    fn trace(&self, o: Vec3, d: Vec3) -> Option<Hit> {
        let ntri = self.tris.len();
        let mut uv = (0.0f32, 0.0f32);
        let mut best_uv = uv;
        let hit = self.bvh.closest(o, d, f32::INFINITY, |p, tmax| {
            let p = p as usize;
            let r = if p < ntri {
                self.hit_tri(p, o, d, tmax).map(|(t, u, v)| {
                    uv = (u, v);
                    t
                })
            } else {
                self.hit_seg(p - ntri, o, d, tmax).map(|(t, s)| {
                    uv = (s, 0.0);
                    t
                })
            };
            if r.is_some() {
                best_uv = uv;
            }
            r
        });
        hit.map(|(t, prim)| Hit {
            t,
            prim,
            u: best_uv.0,
            v: best_uv.1,
        })
    }

    /// Linear RGB of a hit seen along `d`, and whether it is fur.
    fn shade(&self, h: &Hit, d: Vec3) -> ([f32; 3], bool) {
        let e = -d;
        let ntri = self.tris.len();
        let ls = lights();
        if (h.prim as usize) < ntri {
            let [a, b, c] = self.tris[h.prim as usize];
            let w = [1.0 - h.u - h.v, h.u, h.v];
            let idx = [a, b, c].map(|k| k as usize);
            let mut n = (self.normals[idx[0]] * w[0]
                + self.normals[idx[1]] * w[1]
                + self.normals[idx[2]] * w[2])
                .normalize_or_zero();
            if n.dot(e) < 0.0 {
                n = -n;
            }
            let col: [f32; 3] = std::array::from_fn(|ch| {
                self.vcolor[idx[0]][ch] * w[0]
                    + self.vcolor[idx[1]][ch] * w[1]
                    + self.vcolor[idx[2]][ch] * w[2]
            });
            let shiny = self.shiny[idx[0]] || self.shiny[idx[1]] || self.shiny[idx[2]];
            let mut diff = AMBIENT;
            let mut spec = 0.0;
            for l in &ls {
                diff += l.intensity * n.dot(l.dir).max(0.0);
                if shiny {
                    let hv = (l.dir + e).normalize_or_zero();
                    spec += l.intensity * n.dot(hv).max(0.0).powf(60.0);
                }
            }
            (col.map(|c| c * diff + 0.6 * spec), false)
        } else {
            let s = &self.segs[h.prim as usize - ntri];
            let t = (s.p1 - s.p0).normalize_or_zero();
            let arc = s.s0 + (s.s1 - s.s0) * h.u;
            let ao = 0.45 + 0.55 * arc.max(0.0).powf(0.7);
            let te = t.dot(e);
            let se = (1.0 - te * te).max(0.0).sqrt();
            let mut diff = AMBIENT;
            let mut spec = 0.0;
            for l in &ls {
                let tl = t.dot(l.dir);
                let sl = (1.0 - tl * tl).max(0.0).sqrt();
                diff += l.intensity * sl;
                spec += l.intensity * (sl * se - tl * te).max(0.0).powf(40.0);
            }
            let base = self.strand_color[s.strand as usize];
            (base.map(|c| (c * diff + 0.12 * spec) * ao), true)
        }
    }

    /// Renders one view with `ss x ss` samples per pixel.
    pub fn render(&self, cam: &Camera, ss: u32, seed: u64, view: u64) -> Frame {
        let (w, h) = (cam.width, cam.height);
        let fwd = -cam.c2w.z_axis.truncate().normalize_or_zero();
        let ss = ss.max(1);
        let nsamp = (ss * ss) as f32;
        let rows: Vec<(Vec<f32>, Vec<f32>, Vec<f32>)> = (0..h)
            .into_par_iter()
            .map(|y| {
                let mut rgba = Vec::with_capacity(4 * w as usize);
                let mut fur = Vec::with_capacity(w as usize);
                let mut depth = Vec::with_capacity(w as usize);
                for x in 0..w {
                    let mut acc = [0.0f32; 3];
                    let (mut cov, mut nfur, mut dsum) = (0.0f32, 0.0f32, 0.0f32);
                    let pix = mix(
                        seed ^ mix(view.wrapping_mul(0x1_0000_0001) ^ ((y as u64) << 32 | x as u64))
                    );
                    for k in 0..ss * ss {
                        let hsh = mix(pix ^ k as u64);
                        let jx = (hsh >> 40) as f32 / (1u64 << 24) as f32;
                        let jy = ((hsh >> 16) & 0xff_ffff) as f32 / (1u64 << 24) as f32;
                        let u = x as f32 + ((k % ss) as f32 + jx) / ss as f32;
                        let v = y as f32 + ((k / ss) as f32 + jy) / ss as f32;
                        let (o, d) = cam.ray(u, v);
                        if let Some(hit) = self.trace(o, d) {
                            let (c, is_fur) = self.shade(&hit, d);
                            for ch in 0..3 {
                                acc[ch] += c[ch];
                            }
                            cov += 1.0;
                            nfur += is_fur as u32 as f32;
                            dsum += hit.t * d.dot(fwd);
                        }
                    }
                    if cov > 0.0 {
                        for c in acc {
                            rgba.push(srgb(c / cov));
                        }
                        rgba.push(cov / nsamp);
                        depth.push(dsum / cov);
                    } else {
                        rgba.extend_from_slice(&[0.0; 4]);
                        depth.push(0.0);
                    }
                    fur.push(nfur / nsamp);
                }
                (rgba, fur, depth)
            })
            .collect();
        let mut out = Frame {
            rgba: ImageF32::new(w, h, 4),
            fur: ImageF32::new(w, h, 1),
            depth: ImageF32::new(w, h, 1),
        };
        out.rgba.data.clear();
        out.fur.data.clear();
        out.depth.data.clear();
        for (a, b, c) in rows {
            out.rgba.data.extend(a);
            out.fur.data.extend(b);
            out.depth.data.extend(c);
        }
        out
    }
}

/// Linear -> sRGB transfer, clamped to [0, 1].
pub fn srgb(x: f32) -> f32 {
    let x = x.clamp(0.0, 1.0);
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Mat4;

    fn cam(w: u32) -> Camera {
        let c2w = Mat4::look_at_rh(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y).inverse();
        Camera {
            file_path: String::new(),
            c2w,
            fx: w as f32,
            fy: w as f32,
            cx: w as f32 / 2.0,
            cy: w as f32 / 2.0,
            width: w,
            height: w,
        }
    }

    #[test]
    fn strand_coverage_matches_its_width_and_depth_is_right() {
        // One straight horizontal strand of width 0.1 across the view at z = 0, seen from z = 3.
        let mut s = Strands::new();
        s.push(
            &[
                Vec3::new(-2.0, 0.0, 0.0),
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(2.0, 0.0, 0.0),
            ],
            0,
            0.1,
            [0.5, 0.5, 0.5],
        );
        let mesh = Mesh::default();
        let scene = Scene::new(&mesh, vec![], vec![], &s);
        let c = cam(64);
        let f = scene.render(&c, 4, 1, 0);
        // Total coverage in the central column = projected width in pixels (taper at x = 0 is
        // at the strand's midpoint: radius 0.05 * (1 - 0.35)).
        let col = 32;
        let cov: f32 = (0..64).map(|y| f.rgba.pixel(col, y)[3]).sum();
        let want = 2.0 * 0.05 * (1.0 - 0.7 * 0.5) * 64.0 / 3.0;
        assert!((cov - want).abs() < 0.25 * want, "coverage {cov} vs {want}");
        let y_hit = (0..64).find(|&y| f.rgba.pixel(col, y)[3] > 0.0).unwrap();
        let dep = f.depth.pixel(col, y_hit)[0];
        assert!((dep - 3.0).abs() < 0.05, "depth {dep}");
        assert!(f.fur.pixel(col, y_hit)[0] > 0.0);
        assert_eq!(f.rgba.pixel(0, 0)[3], 0.0);
    }

    #[test]
    fn triangle_hits_and_shading_are_finite() {
        let mesh = Mesh {
            positions: vec![
                Vec3::new(-1.0, -1.0, 0.0),
                Vec3::new(1.0, -1.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
            ],
            normals: vec![Vec3::Z; 3],
            triangles: vec![[0, 1, 2]],
            part: vec![0; 3],
            part_names: vec!["skin".into()],
        };
        let scene = Scene::new(
            &mesh,
            vec![[0.8, 0.2, 0.2]; 3],
            vec![false; 3],
            &Strands::new(),
        );
        let f = scene.render(&cam(32), 2, 1, 0);
        assert_eq!(f.rgba.pixel(16, 16)[3], 1.0);
        assert!(f.rgba.pixel(16, 16)[0] > f.rgba.pixel(16, 16)[1]);
        assert!(f
            .rgba
            .data
            .iter()
            .all(|v| v.is_finite() && *v >= 0.0 && *v <= 1.0));
        assert_eq!(f.fur.pixel(16, 16)[0], 0.0);
    }
}
