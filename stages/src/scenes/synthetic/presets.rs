//! Species presets: body proportions (in centimetres), per-part fur and colour patterns.
//!
//! Every preset is built by one parametric quadruped (`Dims` -> primitives) so the animals
//! differ only in numbers: body length and height, head, muzzle, ears, legs, tail, eye separation,
//! plus species extras (the bison's hump, horns and hooves). Sizes are those of a typical adult:
//! tiger 190 cm nose to rump, panda 150 cm, bison 300 cm, fox 65 cm, cat 46 cm, wolf 120 cm,
//! lynx 100 cm. The wolf is the held-out shape: long legs under a short, deep chest, a long
//! muzzle, a winter coat with a long neck ruff and a long bushy tail, and grey colours no other
//! preset has. The lynx is the coat that stands up: its fur leaves the skin at 40-50 degrees
//! (every other preset's at 8-35), with almost no gravity, on a short-tailed cat body. The
//! sheepdog is the coat that hides its body: 5-12 cm of wavy, clumped hair on every part, head
//! and legs included, hanging under its own weight (sheepdog 105 cm). The poodle is the coat
//! that curls: 4-7 cm of tightly curled hair standing off a long-legged dog (curl 0.7-0.8, where
//! the sheepdog's waves are 0.15 and the bison's mane 0.5; poodle 90 cm).
//!
//! Fur lengths per part are chosen so that the mean GT strand length is near the paper's table
//! (Artemis: panda 5.22 cm, fox 3.80 cm, cat 1.60 cm, white tiger 3.70 cm); the bison gets long
//! shaggy fur on head, neck and hump and short fur on the legs.
//!
//! Coordinates: x points from tail to nose, y up (ground at y = 0), z to the animal's left.

use std::collections::BTreeMap;

use fure_stage_api::{StageError, Value};
use glam::{Quat, Vec3};

/// The presets the stage offers.
pub const PRESETS: &[&str] = &[
    "tiger", "fox", "cat", "panda", "bison", "wolf", "lynx", "sheepdog", "poodle",
];

/// Keys a `parts.<name>` override table may hold.
pub const OVERRIDE_KEYS: &[&str] = &[
    "length_cm",
    "length_jitter",
    "density",
    "density_per_cm2",
    "direction",
    "lift_deg",
    "curl",
    "clump",
    "gravity",
    "color",
];

/// Fur of one part. Non-fur parts keep `length_cm = 0` and only use `color`.
#[derive(Debug, Clone, PartialEq)]
pub struct FurParams {
    /// Whether the part grows fur at all (eyes, nose, pads, horns, hooves do not).
    pub fur: bool,
    /// Mean strand length (cm).
    pub length_cm: f32,
    /// Strand lengths are uniform in `length_cm * [1 - j, 1 + j]` (mean preserved).
    pub length_jitter: f32,
    /// Relative root density (multiplies the footprint-derived base density).
    pub density: f32,
    /// Absolute root density (strands per cm^2); when set it replaces the footprint rule.
    pub density_per_cm2: Option<f32>,
    /// Growth direction in the animal frame; `None` uses the body's head-to-tail flow field.
    pub direction: Option<Vec3>,
    /// Angle (degrees) between the first segment and the skin's tangent plane.
    pub lift_deg: f32,
    /// Curl: tangent of the angle by which the strand direction circles its base direction.
    pub curl: f32,
    /// Clumping strength in [0, 1]: how far tips move toward their clump centre.
    pub clump: f32,
    /// Gravity in [0, 1]: how strongly the strand bends downward toward its tip.
    pub gravity: f32,
    /// Base colour (linear RGB in [0, 1]) before the species pattern.
    pub color: [f32; 3],
}

impl FurParams {
    const fn fur(
        length_cm: f32,
        lift_deg: f32,
        curl: f32,
        clump: f32,
        gravity: f32,
        color: [f32; 3],
    ) -> Self {
        FurParams {
            fur: true,
            length_cm,
            length_jitter: 0.2,
            density: 1.0,
            density_per_cm2: None,
            direction: None,
            lift_deg,
            curl,
            clump,
            gravity,
            color,
        }
    }
    const fn bare(color: [f32; 3]) -> Self {
        FurParams {
            fur: false,
            length_cm: 0.0,
            length_jitter: 0.0,
            density: 0.0,
            density_per_cm2: None,
            direction: None,
            lift_deg: 0.0,
            curl: 0.0,
            clump: 0.0,
            gravity: 0.0,
            color,
        }
    }
}

/// An implicit primitive of the body, in centimetres.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    /// Ellipsoid with centre, semi-axes (local frame) and rotation local -> world.
    Ellipsoid { c: Vec3, r: Vec3, rot: Quat },
    /// Capsule with linearly varying radius (round cone) from `a` (radius `ra`) to `b` (`rb`).
    RoundCone { a: Vec3, b: Vec3, ra: f32, rb: f32 },
}

/// One body primitive with its part and fur flow.
#[derive(Debug, Clone, PartialEq)]
pub struct PrimSpec {
    pub shape: Shape,
    pub part: &'static str,
    /// Smooth-union radius (cm) with the primitives before it; 0 is a hard union.
    pub blend: f32,
    /// Lateral squash: the shape is scaled by `factor` along `axis` about its centre.
    pub squash: Option<(Vec3, f32)>,
    /// Direction fur flows over this primitive (head to tail, down the legs, base to tip).
    pub flow: Vec3,
}

/// Colour pattern families.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pattern {
    /// Dark vertical stripes (tiger: black on orange, contrast 1).
    Stripes,
    /// Low-contrast mackerel tabby.
    Tabby,
    /// Panda: black legs, ears, shoulder band and eye patches on white.
    Panda,
    /// Fox: white chin, chest and tail tip, dark lower legs.
    Fox,
    /// Bison: lighter golden hump and head over dark brown.
    Bison,
    /// Wolf: grey agouti with a dark saddle on the back and a cream underside and muzzle.
    Wolf,
}

/// A species preset: geometry, fur and appearance, all in centimetres.
#[derive(Debug, Clone)]
pub struct Preset {
    pub name: &'static str,
    /// Nose-to-rump length (cm); the scene unit is half of it (`s_cm = length / 2`).
    pub body_length_cm: f32,
    /// Eye centres (cm).
    pub eyes_cm: [Vec3; 2],
    pub prims: Vec<PrimSpec>,
    /// Parts in label order (first appearance in `prims`), with their fur.
    pub parts: Vec<(&'static str, FurParams)>,
    pub pattern: Pattern,
    /// Tail base and tip (cm), for patterns that depend on the position along the tail.
    pub tail: (Vec3, Vec3),
    /// Shoulder x (cm), for the panda's band.
    pub shoulder_x: f32,
}

impl Preset {
    /// Species eye separation (cm), distance of the two eye centres by construction.
    pub fn eye_separation_cm(&self) -> f32 {
        (self.eyes_cm[0] - self.eyes_cm[1]).length()
    }
    pub fn part_index(&self, name: &str) -> Option<usize> {
        self.parts.iter().position(|(n, _)| *n == name)
    }
}

/// Proportions of the parametric quadruped (cm, radians).
#[derive(Debug, Clone)]
struct Dims {
    body_length: f32,
    /// Height of the torso centre line above the ground.
    torso_y: f32,
    /// Chest centre to hip centre.
    torso_len: f32,
    chest_r: f32,
    hip_r: f32,
    /// Lateral (z) squash of the torso.
    torso_squash: f32,
    neck_len: f32,
    neck_r: f32,
    /// Angle of the neck above horizontal.
    neck_rise: f32,
    head_r: f32,
    muzzle_len: f32,
    muzzle_r: f32,
    ear_len: f32,
    ear_r: f32,
    /// Tip radius / base radius (pointed 0.25, round 0.9).
    ear_taper: f32,
    eye_r: f32,
    eye_sep: f32,
    leg_r: f32,
    paw_r: f32,
    tail_len: f32,
    tail_r: f32,
    /// Tail angle below horizontal at the base, and its change per segment.
    tail_droop: f32,
    tail_curve: f32,
    hooves: bool,
    hump: bool,
    horns: bool,
}

const EYE_COLOR: [f32; 3] = [0.35, 0.25, 0.05];
const NOSE_COLOR: [f32; 3] = [0.08, 0.06, 0.06];
const PAD_COLOR: [f32; 3] = [0.12, 0.09, 0.09];

fn flat(c: Vec3, r: Vec3) -> Shape {
    Shape::Ellipsoid {
        c,
        r,
        rot: Quat::IDENTITY,
    }
}

/// The quadruped's primitives in order (their union is the body), eye
/// centres, and tail base and tip.
fn build_body(d: &Dims) -> (Vec<PrimSpec>, [Vec3; 2], (Vec3, Vec3)) {
    let mut p = Prims(Vec::new());
    let (hip, head) = trunk(&mut p, d);
    ears(&mut p, d, &head);
    horns(&mut p, d, &head);
    legs(&mut p, d);
    let tail = tail(&mut p, d, hip);
    let eyes = face(&mut p, d, &head);
    let _ = d.body_length;
    (p.0, eyes, tail)
}

/// The primitives of a body, in the order they are added.
struct Prims(Vec<PrimSpec>);

impl Prims {
    fn push(
        &mut self,
        shape: Shape,
        part: &'static str,
        blend: f32,
        squash: Option<(Vec3, f32)>,
        flow: Vec3,
    ) {
        self.0.push(PrimSpec {
            shape,
            part,
            blend,
            squash,
            flow: flow.normalize_or_zero(),
        })
    }
}

/// Where the head is: centre, semi-axes, and the muzzle tip.
struct Head {
    hc: Vec3,
    hr: Vec3,
    m_tip: Vec3,
}

/// Torso, hump, belly, neck, head and muzzle; the hip centre and the head.
fn trunk(p: &mut Prims, d: &Dims) -> (Vec3, Head) {
    let x_chest = d.torso_len * 0.5;
    let x_hip = -d.torso_len * 0.5;
    let yc = d.torso_y;
    let lat = Vec3::Z;
    // Torso: chest -> hip (fur flows head to tail).
    let chest = Vec3::new(x_chest, yc, 0.0);
    let hip = Vec3::new(x_hip, yc + 0.05 * d.hip_r, 0.0);
    p.push(
        Shape::RoundCone {
            a: chest,
            b: hip,
            ra: d.chest_r,
            rb: d.hip_r,
        },
        "torso",
        0.0,
        Some((lat, d.torso_squash)),
        hip - chest,
    );
    if d.hump {
        p.push(
            flat(
                Vec3::new(x_chest - 0.15 * d.torso_len, yc + 0.7 * d.chest_r, 0.0),
                Vec3::new(
                    0.5 * d.torso_len,
                    0.65 * d.chest_r,
                    0.6 * d.chest_r * d.torso_squash,
                ),
            ),
            "shoulders",
            0.25 * d.chest_r,
            None,
            Vec3::new(-1.0, -0.3, 0.0),
        );
    }
    // Belly under the torso.
    p.push(
        flat(
            Vec3::new(0.05 * d.torso_len, yc - 0.42 * d.chest_r, 0.0),
            Vec3::new(
                0.45 * d.torso_len,
                0.6 * d.chest_r,
                0.72 * d.chest_r * d.torso_squash,
            ),
        ),
        "belly",
        0.2 * d.chest_r,
        None,
        Vec3::new(-1.0, 0.0, 0.0),
    );
    // Neck: from the head down to the chest.
    let neck_top = chest
        + Vec3::new(
            d.neck_len * d.neck_rise.cos(),
            d.neck_len * d.neck_rise.sin(),
            0.0,
        )
        + Vec3::new(0.0, 0.2 * d.chest_r, 0.0);
    let neck_base = chest + Vec3::new(-0.1 * d.chest_r, 0.15 * d.chest_r, 0.0);
    p.push(
        Shape::RoundCone {
            a: neck_top,
            b: neck_base,
            ra: d.neck_r,
            rb: 0.85 * d.chest_r * d.torso_squash.max(0.8),
        },
        "neck",
        0.3 * d.neck_r,
        Some((lat, d.torso_squash.max(0.85))),
        neck_base - neck_top,
    );
    // Head.
    let hc = neck_top + Vec3::new(0.35 * d.head_r, 0.15 * d.head_r, 0.0);
    let hr = Vec3::new(1.05 * d.head_r, 0.92 * d.head_r, 0.95 * d.head_r);
    p.push(
        flat(hc, hr),
        "head",
        0.35 * d.head_r,
        None,
        Vec3::new(-1.0, -0.1, 0.0),
    );
    // Muzzle: tip -> base (fur flows back from the nose).
    let m_base = hc + Vec3::new(0.35 * d.head_r, -0.2 * d.head_r, 0.0);
    let m_tip = hc + Vec3::new(0.75 * d.head_r + d.muzzle_len, -0.3 * d.head_r, 0.0);
    p.push(
        Shape::RoundCone {
            a: m_tip,
            b: m_base,
            ra: 0.72 * d.muzzle_r,
            rb: d.muzzle_r,
        },
        "muzzle",
        0.3 * d.muzzle_r,
        None,
        m_base - m_tip,
    );
    (hip, Head { hc, hr, m_tip })
}

/// The ears.
fn ears(p: &mut Prims, d: &Dims, head: &Head) {
    let Head { hc, hr, .. } = *head;
    // Ears: base -> tip, flattened front to back.
    for side in [1.0f32, -1.0] {
        let base = hc + Vec3::new(-0.1 * d.head_r, 0.7 * hr.y, side * 0.5 * hr.z);
        let dir = Vec3::new(-0.15, 1.0, side * 0.35).normalize();
        let tip = base + dir * d.ear_len;
        p.push(
            Shape::RoundCone {
                a: base,
                b: tip,
                ra: d.ear_r,
                rb: d.ear_r * d.ear_taper,
            },
            "ears",
            0.15 * d.ear_r,
            Some((Vec3::X, 0.4)),
            tip - base,
        );
    }
}

/// The horns, when the preset has them (bison): from the head sides, out and up.
fn horns(p: &mut Prims, d: &Dims, head: &Head) {
    let Head { hc, hr, .. } = *head;
    if d.horns {
        for side in [1.0f32, -1.0] {
            let a = hc + Vec3::new(0.1 * d.head_r, 0.45 * hr.y, side * 0.8 * hr.z);
            let b = a + Vec3::new(0.1, 0.6, side * 0.8).normalize() * 0.55 * d.head_r;
            let c = b + Vec3::new(0.2, 1.0, -side * 0.2).normalize() * 0.35 * d.head_r;
            p.push(
                Shape::RoundCone {
                    a,
                    b,
                    ra: 0.16 * d.head_r,
                    rb: 0.1 * d.head_r,
                },
                "horns",
                0.0,
                None,
                b - a,
            );
            p.push(
                Shape::RoundCone {
                    a: b,
                    b: c,
                    ra: 0.1 * d.head_r,
                    rb: 0.03 * d.head_r,
                },
                "horns",
                0.0,
                None,
                c - b,
            );
        }
    }
}

/// Legs, paws and pads, or hooves.
fn legs(p: &mut Prims, d: &Dims) {
    let x_chest = d.torso_len * 0.5;
    let x_hip = -d.torso_len * 0.5;
    let yc = d.torso_y;
    // Legs and paws.
    let zl = 0.6 * d.chest_r * d.torso_squash;
    let paw_y = 0.75 * d.paw_r;
    let xf = x_chest - 0.05 * d.torso_len;
    let xh = x_hip + 0.1 * d.hip_r;
    for side in [1.0f32, -1.0] {
        let z = side * zl;
        // Front: shoulder -> elbow -> wrist.
        let s0 = Vec3::new(xf, yc - 0.1 * d.chest_r, z);
        let s1 = Vec3::new(xf - 0.05 * yc, 0.5 * yc, z);
        let s2 = Vec3::new(xf, 1.1 * paw_y, z);
        p.push(
            Shape::RoundCone {
                a: s0,
                b: s1,
                ra: 1.35 * d.leg_r,
                rb: d.leg_r,
            },
            "front_legs",
            0.5 * d.leg_r,
            None,
            s1 - s0,
        );
        p.push(
            Shape::RoundCone {
                a: s1,
                b: s2,
                ra: d.leg_r,
                rb: 0.8 * d.leg_r,
            },
            "front_legs",
            0.3 * d.leg_r,
            None,
            s2 - s1,
        );
        // Hind: hip -> hock -> ankle.
        let h0 = Vec3::new(xh, yc, z);
        let h1 = Vec3::new(xh - 0.18 * yc, 0.35 * yc, z);
        let h2 = Vec3::new(xh - 0.08 * yc, 1.1 * paw_y, z);
        p.push(
            Shape::RoundCone {
                a: h0,
                b: h1,
                ra: 0.6 * d.hip_r,
                rb: 0.9 * d.leg_r,
            },
            "hind_legs",
            0.5 * d.leg_r,
            None,
            h1 - h0,
        );
        p.push(
            Shape::RoundCone {
                a: h1,
                b: h2,
                ra: 0.9 * d.leg_r,
                rb: 0.8 * d.leg_r,
            },
            "hind_legs",
            0.3 * d.leg_r,
            None,
            h2 - h1,
        );
        for foot in [s2, h2] {
            let pc = Vec3::new(foot.x + 0.3 * d.paw_r, paw_y, z);
            if d.hooves {
                p.push(
                    Shape::RoundCone {
                        a: Vec3::new(pc.x, paw_y * 1.1, z),
                        b: Vec3::new(pc.x + 0.2 * d.paw_r, 0.3 * d.paw_r, z),
                        ra: 0.85 * d.paw_r,
                        rb: 0.3 * d.paw_r + 0.0 * d.paw_r,
                    },
                    "hooves",
                    0.0,
                    None,
                    Vec3::new(0.0, -1.0, 0.0),
                );
            } else {
                p.push(
                    flat(pc, Vec3::new(1.3 * d.paw_r, 0.75 * d.paw_r, d.paw_r)),
                    "paws",
                    0.3 * d.paw_r,
                    None,
                    Vec3::X,
                );
                p.push(
                    flat(
                        Vec3::new(pc.x, 0.12 * d.paw_r, z),
                        Vec3::new(0.95 * d.paw_r, 0.2 * d.paw_r, 0.72 * d.paw_r),
                    ),
                    "pads",
                    0.0,
                    None,
                    Vec3::X,
                );
            }
        }
    }
}

/// The tail from the rump; its base and tip.
fn tail(p: &mut Prims, d: &Dims, hip: Vec3) -> (Vec3, Vec3) {
    // Tail: three round cones from the rump, drooping and curving.
    let mut a = hip + Vec3::new(-0.8 * d.hip_r, 0.35 * d.hip_r, 0.0);
    let tail_base = a;
    let mut r = d.tail_r;
    for i in 0..3 {
        let ang = d.tail_droop + i as f32 * d.tail_curve;
        let b = a + Vec3::new(-ang.cos(), -ang.sin(), 0.0) * (d.tail_len / 3.0);
        let rb = r * 0.8;
        p.push(
            Shape::RoundCone { a, b, ra: r, rb },
            "tail",
            if i == 0 { 0.4 * d.tail_r } else { 0.2 * r },
            None,
            b - a,
        );
        a = b;
        r = rb;
    }
    (tail_base, a)
}

/// Nose and eyes (hard unions, added last); the eye centres.
fn face(p: &mut Prims, d: &Dims, head: &Head) -> [Vec3; 2] {
    let Head { hc, hr, m_tip } = *head;
    // Nose at the muzzle tip, eyes on the head surface (hard unions, added last).
    p.push(
        flat(
            m_tip + Vec3::new(0.55 * 0.72 * d.muzzle_r, 0.3 * d.muzzle_r, 0.0),
            Vec3::new(0.28, 0.24, 0.36) * d.muzzle_r,
        ),
        "nose",
        0.0,
        None,
        Vec3::X,
    );
    let mut eyes = [Vec3::ZERO; 2];
    for (k, side) in [1.0f32, -1.0].into_iter().enumerate() {
        let dy = 0.22 * hr.y;
        let dz = side * 0.5 * d.eye_sep;
        let q = 1.0 - (dy / hr.y).powi(2) - (dz / hr.z).powi(2);
        let dx = hr.x * q.max(0.05).sqrt() - 0.45 * d.eye_r;
        let c = hc + Vec3::new(dx, dy, dz);
        eyes[k] = c;
        p.push(
            Shape::Ellipsoid {
                c,
                r: Vec3::splat(d.eye_r),
                rot: Quat::IDENTITY,
            },
            "eyes",
            0.0,
            None,
            Vec3::X,
        );
    }
    eyes
}

/// One preset's data: proportions, the fur of its parts (any order: the
/// label order is the primitives') and colour pattern.
struct PresetData {
    name: &'static str,
    dims: Dims,
    parts: &'static [(&'static str, FurParams)],
    pattern: Pattern,
}

/// Every preset's data, in [`PRESETS`] order.
const PRESET_DATA: [&PresetData; 9] = [
    &TIGER, &FOX, &CAT, &PANDA, &BISON, &WOLF, &LYNX, &SHEEPDOG, &POODLE,
];

const TIGER: PresetData = {
    const O: [f32; 3] = [0.85, 0.42, 0.12];
    const W: [f32; 3] = [0.9, 0.88, 0.82];
    PresetData {
        name: "tiger",
        dims: Dims {
            body_length: 190.0,
            torso_y: 68.0,
            torso_len: 85.0,
            chest_r: 30.0,
            hip_r: 25.0,
            torso_squash: 0.78,
            neck_len: 24.0,
            neck_r: 18.0,
            neck_rise: 0.45,
            head_r: 15.0,
            muzzle_len: 7.0,
            muzzle_r: 8.5,
            ear_len: 8.0,
            ear_r: 4.0,
            ear_taper: 0.6,
            eye_r: 1.8,
            eye_sep: 8.5,
            leg_r: 8.5,
            paw_r: 7.5,
            tail_len: 90.0,
            tail_r: 5.0,
            tail_droop: 0.9,
            tail_curve: -0.35,
            hooves: false,
            hump: false,
            horns: false,
        },
        parts: &[
            ("torso", FurParams::fur(4.25, 16.0, 0.05, 0.3, 0.2, O)),
            ("belly", FurParams::fur(5.0, 20.0, 0.08, 0.35, 0.35, W)),
            ("neck", FurParams::fur(4.9, 20.0, 0.05, 0.3, 0.2, O)),
            ("head", FurParams::fur(2.85, 14.0, 0.0, 0.2, 0.1, O)),
            ("muzzle", FurParams::fur(1.5, 12.0, 0.0, 0.1, 0.05, W)),
            ("ears", FurParams::fur(1.6, 12.0, 0.0, 0.1, 0.0, O)),
            ("front_legs", FurParams::fur(3.05, 14.0, 0.0, 0.2, 0.1, O)),
            ("hind_legs", FurParams::fur(3.05, 14.0, 0.0, 0.2, 0.1, O)),
            ("paws", FurParams::fur(1.95, 12.0, 0.0, 0.1, 0.0, O)),
            ("pads", FurParams::bare(PAD_COLOR)),
            ("tail", FurParams::fur(3.9, 18.0, 0.05, 0.3, 0.1, O)),
            ("nose", FurParams::bare([0.55, 0.3, 0.3])),
            ("eyes", FurParams::bare(EYE_COLOR)),
        ],
        pattern: Pattern::Stripes,
    }
};

const FOX: PresetData = {
    const O: [f32; 3] = [0.8, 0.3, 0.06];
    const W: [f32; 3] = [0.92, 0.9, 0.86];
    PresetData {
        name: "fox",
        dims: Dims {
            body_length: 65.0,
            torso_y: 28.0,
            torso_len: 30.0,
            chest_r: 9.5,
            hip_r: 8.0,
            torso_squash: 0.8,
            neck_len: 9.0,
            neck_r: 5.5,
            neck_rise: 0.6,
            head_r: 5.5,
            muzzle_len: 6.0,
            muzzle_r: 2.4,
            ear_len: 6.5,
            ear_r: 2.6,
            ear_taper: 0.2,
            eye_r: 0.8,
            eye_sep: 4.0,
            leg_r: 2.2,
            paw_r: 2.2,
            tail_len: 38.0,
            tail_r: 3.2,
            tail_droop: 0.5,
            tail_curve: 0.1,
            hooves: false,
            hump: false,
            horns: false,
        },
        parts: &[
            ("torso", FurParams::fur(4.35, 24.0, 0.1, 0.35, 0.25, O)),
            ("belly", FurParams::fur(4.15, 24.0, 0.1, 0.35, 0.3, W)),
            ("neck", FurParams::fur(5.0, 28.0, 0.1, 0.4, 0.25, O)),
            ("head", FurParams::fur(2.2, 18.0, 0.0, 0.2, 0.1, O)),
            ("muzzle", FurParams::fur(1.1, 12.0, 0.0, 0.1, 0.0, O)),
            ("ears", FurParams::fur(1.3, 12.0, 0.0, 0.1, 0.0, O)),
            ("front_legs", FurParams::fur(2.2, 14.0, 0.0, 0.2, 0.1, O)),
            ("hind_legs", FurParams::fur(2.6, 16.0, 0.0, 0.2, 0.1, O)),
            ("paws", FurParams::fur(1.3, 10.0, 0.0, 0.1, 0.0, O)),
            ("pads", FurParams::bare(PAD_COLOR)),
            ("tail", FurParams::fur(7.1, 35.0, 0.12, 0.45, 0.25, O)),
            ("nose", FurParams::bare(NOSE_COLOR)),
            ("eyes", FurParams::bare(EYE_COLOR)),
        ],
        pattern: Pattern::Fox,
    }
};

const CAT: PresetData = {
    const G: [f32; 3] = [0.5, 0.45, 0.38];
    PresetData {
        name: "cat",
        dims: Dims {
            body_length: 46.0,
            torso_y: 20.0,
            torso_len: 21.0,
            chest_r: 7.0,
            hip_r: 6.3,
            torso_squash: 0.8,
            neck_len: 5.5,
            neck_r: 4.2,
            neck_rise: 0.55,
            head_r: 4.6,
            muzzle_len: 1.2,
            muzzle_r: 2.2,
            ear_len: 3.6,
            ear_r: 1.7,
            ear_taper: 0.25,
            eye_r: 0.9,
            eye_sep: 3.3,
            leg_r: 1.6,
            paw_r: 1.6,
            tail_len: 28.0,
            tail_r: 1.5,
            tail_droop: 0.2,
            tail_curve: -0.5,
            hooves: false,
            hump: false,
            horns: false,
        },
        parts: &[
            ("torso", FurParams::fur(1.85, 10.0, 0.0, 0.2, 0.05, G)),
            (
                "belly",
                FurParams::fur(2.05, 12.0, 0.05, 0.2, 0.1, [0.75, 0.7, 0.62]),
            ),
            ("neck", FurParams::fur(1.85, 10.0, 0.0, 0.2, 0.05, G)),
            ("head", FurParams::fur(1.15, 8.0, 0.0, 0.1, 0.0, G)),
            (
                "muzzle",
                FurParams::fur(0.6, 8.0, 0.0, 0.05, 0.0, [0.8, 0.78, 0.72]),
            ),
            ("ears", FurParams::fur(0.6, 8.0, 0.0, 0.05, 0.0, G)),
            ("front_legs", FurParams::fur(1.35, 8.0, 0.0, 0.1, 0.05, G)),
            ("hind_legs", FurParams::fur(1.45, 8.0, 0.0, 0.1, 0.05, G)),
            ("paws", FurParams::fur(0.8, 8.0, 0.0, 0.05, 0.0, G)),
            ("pads", FurParams::bare([0.45, 0.25, 0.28])),
            ("tail", FurParams::fur(1.85, 12.0, 0.0, 0.2, 0.05, G)),
            ("nose", FurParams::bare([0.55, 0.3, 0.32])),
            ("eyes", FurParams::bare([0.45, 0.4, 0.05])),
        ],
        pattern: Pattern::Tabby,
    }
};

const PANDA: PresetData = {
    const W: [f32; 3] = [0.88, 0.87, 0.82];
    const K: [f32; 3] = [0.05, 0.05, 0.05];
    PresetData {
        name: "panda",
        dims: Dims {
            body_length: 150.0,
            torso_y: 50.0,
            torso_len: 62.0,
            chest_r: 29.0,
            hip_r: 28.0,
            torso_squash: 0.85,
            neck_len: 12.0,
            neck_r: 20.0,
            neck_rise: 0.25,
            head_r: 19.0,
            muzzle_len: 3.0,
            muzzle_r: 7.5,
            ear_len: 4.0,
            ear_r: 4.5,
            ear_taper: 0.9,
            eye_r: 1.6,
            eye_sep: 10.0,
            leg_r: 10.0,
            paw_r: 9.0,
            tail_len: 14.0,
            tail_r: 5.0,
            tail_droop: 0.9,
            tail_curve: 0.2,
            hooves: false,
            hump: false,
            horns: false,
        },
        parts: &[
            ("torso", FurParams::fur(5.8, 30.0, 0.15, 0.4, 0.3, W)),
            ("belly", FurParams::fur(5.6, 30.0, 0.15, 0.4, 0.35, W)),
            ("neck", FurParams::fur(5.8, 30.0, 0.15, 0.4, 0.3, W)),
            ("head", FurParams::fur(4.4, 25.0, 0.1, 0.3, 0.2, W)),
            ("muzzle", FurParams::fur(2.1, 15.0, 0.0, 0.1, 0.05, W)),
            ("ears", FurParams::fur(3.1, 25.0, 0.1, 0.2, 0.1, K)),
            ("front_legs", FurParams::fur(5.2, 25.0, 0.15, 0.4, 0.3, K)),
            ("hind_legs", FurParams::fur(5.2, 25.0, 0.15, 0.4, 0.3, K)),
            ("paws", FurParams::fur(3.1, 18.0, 0.1, 0.2, 0.1, K)),
            ("pads", FurParams::bare(PAD_COLOR)),
            ("tail", FurParams::fur(4.2, 25.0, 0.1, 0.3, 0.2, W)),
            ("nose", FurParams::bare(NOSE_COLOR)),
            ("eyes", FurParams::bare([0.1, 0.07, 0.05])),
        ],
        pattern: Pattern::Panda,
    }
};

const BISON: PresetData = {
    const B: [f32; 3] = [0.06, 0.035, 0.02];
    const G: [f32; 3] = [0.2, 0.11, 0.045];
    PresetData {
        name: "bison",
        dims: Dims {
            body_length: 300.0,
            torso_y: 105.0,
            torso_len: 130.0,
            chest_r: 50.0,
            hip_r: 38.0,
            torso_squash: 0.75,
            neck_len: 30.0,
            neck_r: 34.0,
            neck_rise: -0.35,
            head_r: 28.0,
            muzzle_len: 10.0,
            muzzle_r: 14.0,
            ear_len: 8.0,
            ear_r: 5.0,
            ear_taper: 0.5,
            eye_r: 2.4,
            eye_sep: 25.0,
            leg_r: 11.0,
            paw_r: 9.0,
            tail_len: 50.0,
            tail_r: 4.0,
            tail_droop: 1.3,
            tail_curve: 0.05,
            hooves: true,
            hump: true,
            horns: true,
        },
        parts: &[
            ("torso", FurParams::fur(4.0, 25.0, 0.3, 0.4, 0.3, B)),
            ("shoulders", FurParams::fur(14.0, 45.0, 0.5, 0.6, 0.5, G)),
            ("belly", FurParams::fur(5.0, 30.0, 0.4, 0.5, 0.5, B)),
            ("neck", FurParams::fur(12.0, 45.0, 0.5, 0.6, 0.5, G)),
            ("head", FurParams::fur(11.0, 45.0, 0.5, 0.6, 0.4, B)),
            ("muzzle", FurParams::fur(2.5, 20.0, 0.2, 0.3, 0.2, B)),
            ("ears", FurParams::fur(3.0, 20.0, 0.2, 0.3, 0.2, B)),
            ("horns", FurParams::bare([0.12, 0.11, 0.1])),
            ("front_legs", FurParams::fur(3.0, 20.0, 0.2, 0.3, 0.3, B)),
            ("hind_legs", FurParams::fur(2.0, 15.0, 0.1, 0.2, 0.2, B)),
            ("hooves", FurParams::bare([0.06, 0.05, 0.05])),
            ("tail", FurParams::fur(8.0, 20.0, 0.4, 0.5, 0.6, B)),
            ("nose", FurParams::bare(NOSE_COLOR)),
            ("eyes", FurParams::bare([0.08, 0.05, 0.04])),
        ],
        pattern: Pattern::Bison,
    }
};

const WOLF: PresetData = {
    const G: [f32; 3] = [0.46, 0.43, 0.39];
    const C: [f32; 3] = [0.86, 0.81, 0.72];
    PresetData {
        name: "wolf",
        dims: Dims {
            body_length: 120.0,
            torso_y: 56.0,
            torso_len: 52.0,
            chest_r: 17.0,
            hip_r: 12.5,
            torso_squash: 0.7,
            neck_len: 16.0,
            neck_r: 10.0,
            neck_rise: 0.5,
            head_r: 9.0,
            muzzle_len: 12.0,
            muzzle_r: 3.8,
            ear_len: 8.0,
            ear_r: 3.2,
            ear_taper: 0.25,
            eye_r: 1.2,
            eye_sep: 6.0,
            leg_r: 4.0,
            paw_r: 4.2,
            tail_len: 45.0,
            tail_r: 4.5,
            tail_droop: 1.1,
            tail_curve: 0.05,
            hooves: false,
            hump: false,
            horns: false,
        },
        parts: &[
            ("torso", FurParams::fur(6.0, 28.0, 0.05, 0.35, 0.3, G)),
            ("belly", FurParams::fur(4.0, 22.0, 0.05, 0.3, 0.3, C)),
            ("neck", FurParams::fur(8.5, 35.0, 0.1, 0.45, 0.35, G)),
            ("head", FurParams::fur(2.2, 14.0, 0.0, 0.15, 0.05, G)),
            ("muzzle", FurParams::fur(0.9, 10.0, 0.0, 0.05, 0.0, C)),
            ("ears", FurParams::fur(1.8, 14.0, 0.0, 0.1, 0.0, G)),
            ("front_legs", FurParams::fur(1.8, 12.0, 0.0, 0.15, 0.1, C)),
            ("hind_legs", FurParams::fur(2.4, 14.0, 0.0, 0.2, 0.1, G)),
            ("paws", FurParams::fur(1.1, 10.0, 0.0, 0.05, 0.0, C)),
            ("pads", FurParams::bare(PAD_COLOR)),
            ("tail", FurParams::fur(8.0, 30.0, 0.1, 0.45, 0.35, G)),
            ("nose", FurParams::bare(NOSE_COLOR)),
            ("eyes", FurParams::bare([0.55, 0.45, 0.1])),
        ],
        pattern: Pattern::Wolf,
    }
};

/// The coat that stands up: every fur part leaves the skin at 40-50 degrees with
/// little gravity, where the other presets' fur lies at 8-35 degrees, so a default
/// chosen on the dev split has to hold for fur whose elevation training must keep.
const LYNX: PresetData = {
    const T: [f32; 3] = [0.62, 0.52, 0.4];
    const C: [f32; 3] = [0.88, 0.85, 0.78];
    PresetData {
        name: "lynx",
        dims: Dims {
            body_length: 100.0,
            torso_y: 46.0,
            torso_len: 44.0,
            chest_r: 13.0,
            hip_r: 12.0,
            torso_squash: 0.8,
            neck_len: 10.0,
            neck_r: 8.0,
            neck_rise: 0.5,
            head_r: 8.0,
            muzzle_len: 3.0,
            muzzle_r: 3.5,
            ear_len: 7.0,
            ear_r: 2.5,
            ear_taper: 0.2,
            eye_r: 1.2,
            eye_sep: 5.0,
            leg_r: 4.0,
            paw_r: 4.4,
            tail_len: 15.0,
            tail_r: 3.0,
            tail_droop: 0.3,
            tail_curve: -0.2,
            hooves: false,
            hump: false,
            horns: false,
        },
        parts: &[
            ("torso", FurParams::fur(4.0, 45.0, 0.05, 0.3, 0.05, T)),
            ("belly", FurParams::fur(4.5, 45.0, 0.05, 0.3, 0.1, C)),
            ("neck", FurParams::fur(5.0, 50.0, 0.05, 0.35, 0.05, T)),
            ("head", FurParams::fur(2.5, 40.0, 0.0, 0.2, 0.0, T)),
            ("muzzle", FurParams::fur(1.2, 40.0, 0.0, 0.1, 0.0, C)),
            ("ears", FurParams::fur(1.5, 40.0, 0.0, 0.1, 0.0, T)),
            ("front_legs", FurParams::fur(3.0, 40.0, 0.0, 0.2, 0.05, T)),
            ("hind_legs", FurParams::fur(3.0, 40.0, 0.0, 0.2, 0.05, T)),
            ("paws", FurParams::fur(2.5, 40.0, 0.0, 0.1, 0.0, C)),
            ("pads", FurParams::bare(PAD_COLOR)),
            ("tail", FurParams::fur(3.5, 45.0, 0.05, 0.3, 0.05, T)),
            ("nose", FurParams::bare(NOSE_COLOR)),
            ("eyes", FurParams::bare([0.55, 0.45, 0.1])),
        ],
        pattern: Pattern::Tabby,
    }
};

/// The coat that hides the body: long, wavy, clumped hair on every part (head, legs and
/// paws included) that leaves the skin steeply and then hangs, so the outer surface lies far
/// from the skin everywhere and the views see mostly hanging strands.
const SHEEPDOG: PresetData = {
    const G: [f32; 3] = [0.5, 0.52, 0.55];
    const W: [f32; 3] = [0.88, 0.87, 0.84];
    PresetData {
        name: "sheepdog",
        dims: Dims {
            body_length: 105.0,
            torso_y: 48.0,
            torso_len: 46.0,
            chest_r: 15.0,
            hip_r: 14.0,
            torso_squash: 0.85,
            neck_len: 10.0,
            neck_r: 10.0,
            neck_rise: 0.5,
            head_r: 9.5,
            muzzle_len: 7.0,
            muzzle_r: 4.5,
            ear_len: 7.0,
            ear_r: 3.5,
            ear_taper: 0.5,
            eye_r: 1.2,
            eye_sep: 6.0,
            leg_r: 4.5,
            paw_r: 5.0,
            tail_len: 8.0,
            tail_r: 4.0,
            tail_droop: 0.5,
            tail_curve: 0.0,
            hooves: false,
            hump: false,
            horns: false,
        },
        parts: &[
            ("torso", FurParams::fur(11.0, 35.0, 0.15, 0.5, 0.7, G)),
            ("belly", FurParams::fur(10.0, 30.0, 0.15, 0.5, 0.8, W)),
            ("neck", FurParams::fur(12.0, 35.0, 0.15, 0.5, 0.7, W)),
            ("head", FurParams::fur(8.0, 40.0, 0.15, 0.45, 0.6, W)),
            ("muzzle", FurParams::fur(5.0, 35.0, 0.1, 0.4, 0.6, W)),
            ("ears", FurParams::fur(8.0, 30.0, 0.15, 0.5, 0.7, G)),
            ("front_legs", FurParams::fur(7.0, 30.0, 0.15, 0.45, 0.7, W)),
            ("hind_legs", FurParams::fur(8.0, 30.0, 0.15, 0.45, 0.7, G)),
            ("paws", FurParams::fur(5.0, 30.0, 0.1, 0.4, 0.6, W)),
            ("pads", FurParams::bare(PAD_COLOR)),
            ("tail", FurParams::fur(7.0, 35.0, 0.15, 0.5, 0.6, G)),
            ("nose", FurParams::bare(NOSE_COLOR)),
            ("eyes", FurParams::bare([0.3, 0.25, 0.2])),
        ],
        pattern: Pattern::Tabby,
    }
};

/// The coat that curls: every long-haired part is tight curls (a cone of 35-39 degrees
/// around the growth direction, 1.25 turns per strand) standing off the skin, little
/// gravity, light clumping; a short, straight muzzle. Its strands bend at the scale of a
/// pixel or below, where every other dev coat is straight or gently waved.
const POODLE: PresetData = {
    const A: [f32; 3] = [0.78, 0.52, 0.32];
    const L: [f32; 3] = [0.86, 0.66, 0.45];
    PresetData {
        name: "poodle",
        dims: Dims {
            body_length: 90.0,
            torso_y: 52.0,
            torso_len: 38.0,
            chest_r: 12.0,
            hip_r: 10.0,
            torso_squash: 0.85,
            neck_len: 14.0,
            neck_r: 7.0,
            neck_rise: 0.7,
            head_r: 7.0,
            muzzle_len: 9.0,
            muzzle_r: 3.0,
            ear_len: 9.0,
            ear_r: 3.5,
            ear_taper: 0.6,
            eye_r: 1.0,
            eye_sep: 5.0,
            leg_r: 3.2,
            paw_r: 3.5,
            tail_len: 15.0,
            tail_r: 2.5,
            tail_droop: 0.2,
            tail_curve: -0.3,
            hooves: false,
            hump: false,
            horns: false,
        },
        parts: &[
            ("torso", FurParams::fur(5.0, 55.0, 0.8, 0.3, 0.1, A)),
            ("belly", FurParams::fur(4.5, 50.0, 0.8, 0.3, 0.15, L)),
            ("neck", FurParams::fur(5.5, 55.0, 0.8, 0.3, 0.1, A)),
            ("head", FurParams::fur(6.0, 60.0, 0.8, 0.3, 0.1, L)),
            ("muzzle", FurParams::fur(1.0, 15.0, 0.0, 0.0, 0.0, A)),
            ("ears", FurParams::fur(7.0, 45.0, 0.7, 0.4, 0.5, A)),
            ("front_legs", FurParams::fur(4.0, 50.0, 0.7, 0.3, 0.1, L)),
            ("hind_legs", FurParams::fur(4.0, 50.0, 0.7, 0.3, 0.1, A)),
            ("paws", FurParams::fur(2.0, 40.0, 0.5, 0.2, 0.0, L)),
            ("pads", FurParams::bare(PAD_COLOR)),
            ("tail", FurParams::fur(5.0, 55.0, 0.8, 0.3, 0.1, L)),
            ("nose", FurParams::bare(NOSE_COLOR)),
            ("eyes", FurParams::bare([0.2, 0.14, 0.1])),
        ],
        pattern: Pattern::Tabby,
    }
};

/// Builds a preset by name.
pub fn preset(name: &str) -> Result<Preset, StageError> {
    let Some(data) = PRESET_DATA.iter().find(|d| d.name == name) else {
        return Err(StageError::param(
            "preset",
            format!(
                "unknown preset `{name}`; expected one of {}",
                PRESETS.join(", ")
            ),
        ));
    };
    let (dims, parts, pattern) = (&data.dims, data.parts, data.pattern);
    let (prims, eyes_cm, tail) = build_body(dims);
    // Parts in label order: first appearance among the primitives.
    let mut ordered: Vec<(&'static str, FurParams)> = Vec::new();
    for p in &prims {
        if !ordered.iter().any(|(n, _)| *n == p.part) {
            let fur = parts
                .iter()
                .find(|(n, _)| *n == p.part)
                .map(|(_, f)| f.clone())
                .unwrap_or_else(|| FurParams::bare([0.5, 0.5, 0.5]));
            ordered.push((p.part, fur));
        }
    }
    Ok(Preset {
        name: data.name,
        body_length_cm: dims.body_length,
        eyes_cm,
        prims,
        parts: ordered,
        pattern,
        tail,
        shoulder_x: dims.torso_len * 0.5 - 0.05 * dims.torso_len,
    })
}

fn num(part: &str, key: &str, v: &Value, lo: f64, hi: f64) -> Result<f32, StageError> {
    let x = v.as_f64().ok_or_else(|| {
        StageError::param(
            format!("parts.{part}.{key}"),
            format!("expected a number, found {}", v.type_name()),
        )
    })?;
    if !(x.is_finite() && x >= lo && x <= hi) {
        return Err(StageError::param(
            format!("parts.{part}.{key}"),
            format!("expected a number in [{lo}, {hi}], found {x}"),
        ));
    }
    Ok(x as f32)
}

fn vec3(part: &str, key: &str, v: &Value, lo: f64, hi: f64) -> Result<[f32; 3], StageError> {
    let name = format!("parts.{part}.{key}");
    let l = v.as_list().filter(|l| l.len() == 3).ok_or_else(|| {
        StageError::param(
            &name,
            format!("expected an array of 3 numbers, found {}", v.type_name()),
        )
    })?;
    let mut out = [0.0f32; 3];
    for (o, x) in out.iter_mut().zip(l) {
        *o = num(part, key, x, lo, hi)?;
    }
    Ok(out)
}

/// Checks a `parts` override table against a preset without applying it.
pub fn validate_overrides(
    preset: &Preset,
    table: &BTreeMap<String, Value>,
) -> Result<(), StageError> {
    let mut p = preset.clone();
    apply_overrides(&mut p, table)
}

/// Applies `parts.<part>.<key> = value` overrides. Unknown parts or keys are errors that list
/// what is allowed; fur keys on parts without fur are errors too.
pub fn apply_overrides(
    preset: &mut Preset,
    table: &BTreeMap<String, Value>,
) -> Result<(), StageError> {
    let allowed_parts: Vec<&str> = preset.parts.iter().map(|(n, _)| *n).collect();
    for (part, v) in table {
        let idx = preset.part_index(part).ok_or_else(|| {
            StageError::param(
                format!("parts.{part}"),
                format!(
                    "unknown part `{part}` for preset `{}`; parts are: {}",
                    preset.name,
                    allowed_parts.join(", ")
                ),
            )
        })?;
        let t = v.as_table().ok_or_else(|| {
            StageError::param(
                format!("parts.{part}"),
                format!("expected a table, found {}", v.type_name()),
            )
        })?;
        let fp = &mut preset.parts[idx].1;
        for (key, val) in t {
            if !OVERRIDE_KEYS.contains(&key.as_str()) {
                return Err(StageError::param(
                    format!("parts.{part}.{key}"),
                    format!(
                        "unknown key `{key}`; allowed keys are: {}",
                        OVERRIDE_KEYS.join(", ")
                    ),
                ));
            }
            if !fp.fur && key != "color" {
                return Err(StageError::param(
                    format!("parts.{part}.{key}"),
                    format!("part `{part}` carries no fur; only `color` may be set"),
                ));
            }
            match key.as_str() {
                "length_cm" => fp.length_cm = num(part, key, val, 0.05, 100.0)?,
                "length_jitter" => fp.length_jitter = num(part, key, val, 0.0, 0.9)?,
                "density" => fp.density = num(part, key, val, 0.0, 100.0)?,
                "density_per_cm2" => fp.density_per_cm2 = Some(num(part, key, val, 0.0, 1000.0)?),
                "direction" => {
                    let d = Vec3::from(vec3(part, key, val, -1e3, 1e3)?);
                    let n = d.try_normalize().ok_or_else(|| {
                        StageError::param(
                            format!("parts.{part}.direction"),
                            "expected a non-zero vector",
                        )
                    })?;
                    fp.direction = Some(n);
                }
                "lift_deg" => fp.lift_deg = num(part, key, val, 0.0, 90.0)?,
                "curl" => fp.curl = num(part, key, val, 0.0, 3.0)?,
                "clump" => fp.clump = num(part, key, val, 0.0, 1.0)?,
                "gravity" => fp.gravity = num(part, key, val, 0.0, 1.0)?,
                "color" => fp.color = vec3(part, key, val, 0.0, 1.0)?,
                _ => {}
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_build_with_expected_parts() {
        for name in PRESETS {
            let p = preset(name).unwrap();
            for part in [
                "head",
                "ears",
                "muzzle",
                "eyes",
                "nose",
                "neck",
                "torso",
                "belly",
                "front_legs",
                "hind_legs",
                "tail",
            ] {
                assert!(p.part_index(part).is_some(), "{name} lacks {part}");
            }
            assert!(p.eye_separation_cm() > 2.0 && p.eye_separation_cm() < 40.0);
            for (n, f) in &p.parts {
                assert_eq!(
                    f.fur,
                    !["eyes", "nose", "pads", "horns", "hooves"].contains(n),
                    "{name}/{n}"
                );
            }
        }
        assert!(preset("dog").is_err());
    }

    #[test]
    fn overrides_apply_and_reject_unknowns() {
        let mut p = preset("cat").unwrap();
        let mut t = BTreeMap::new();
        let mut torso = BTreeMap::new();
        torso.insert("length_cm".to_string(), Value::Float(4.0));
        torso.insert(
            "color".to_string(),
            Value::List(vec![Value::Float(0.1), Value::Int(1), Value::Float(0.5)]),
        );
        t.insert("torso".to_string(), Value::Table(torso));
        apply_overrides(&mut p, &t).unwrap();
        let f = &p.parts[p.part_index("torso").unwrap()].1;
        assert_eq!(f.length_cm, 4.0);
        assert_eq!(f.color, [0.1, 1.0, 0.5]);

        let mut bad = BTreeMap::new();
        bad.insert("wings".to_string(), Value::Table(BTreeMap::new()));
        let e = apply_overrides(&mut p, &bad).unwrap_err().to_string();
        assert!(e.contains("wings") && e.contains("torso"), "{e}");

        let mut bad = BTreeMap::new();
        let mut k = BTreeMap::new();
        k.insert("lenght_cm".to_string(), Value::Float(1.0));
        bad.insert("torso".to_string(), Value::Table(k));
        let e = apply_overrides(&mut p, &bad).unwrap_err().to_string();
        assert!(e.contains("lenght_cm") && e.contains("length_cm"), "{e}");

        let mut bad = BTreeMap::new();
        let mut k = BTreeMap::new();
        k.insert("length_cm".to_string(), Value::Float(1.0));
        bad.insert("eyes".to_string(), Value::Table(k));
        assert!(apply_overrides(&mut p, &bad)
            .unwrap_err()
            .to_string()
            .contains("no fur"));
    }
}
