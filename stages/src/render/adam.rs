//! Adam (Kingma & Ba) with per-group learning rates.
//!
//! Parameters are grouped (e.g. "means", "scales", "colours"); each group has
//! its own learning rate, moment buffers and step count, and is stepped with
//! [`Adam::step`] on a flat `f32` slice. Bias correction as in the paper; the
//! update is `p -= lr * m_hat / (sqrt(v_hat) + eps)`. Plain sequential loops:
//! deterministic and cheap next to rendering.

use super::RenderError;

/// One parameter group.
#[derive(Debug, Clone, PartialEq)]
pub struct AdamGroup {
    pub name: String,
    pub lr: f32,
    m: Vec<f32>,
    v: Vec<f32>,
    t: u32,
}

impl AdamGroup {
    /// Steps taken so far.
    pub fn steps(&self) -> u32 {
        self.t
    }
    pub fn len(&self) -> usize {
        self.m.len()
    }
    pub fn is_empty(&self) -> bool {
        self.m.is_empty()
    }
}

/// Adam optimiser state for several parameter groups.
#[derive(Debug, Clone, PartialEq)]
pub struct Adam {
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
    groups: Vec<AdamGroup>,
}

impl Default for Adam {
    fn default() -> Self {
        Adam::new(0.9, 0.999, 1e-15)
    }
}

impl Adam {
    /// 3DGS uses eps = 1e-15 (the default); the Adam paper uses 1e-8.
    pub fn new(beta1: f32, beta2: f32, eps: f32) -> Self {
        Adam {
            beta1,
            beta2,
            eps,
            groups: Vec::new(),
        }
    }

    /// Adds a group of `len` parameters with learning rate `lr`; returns its id.
    pub fn add_group(&mut self, name: &str, lr: f32, len: usize) -> usize {
        self.groups.push(AdamGroup {
            name: name.to_string(),
            lr,
            m: vec![0.0; len],
            v: vec![0.0; len],
            t: 0,
        });
        self.groups.len() - 1
    }

    /// Id of the group called `name`.
    pub fn group_id(&self, name: &str) -> Option<usize> {
        self.groups.iter().position(|g| g.name == name)
    }

    pub fn group(&self, id: usize) -> Option<&AdamGroup> {
        self.groups.get(id)
    }

    /// Changes a group's learning rate (schedules).
    pub fn set_lr(&mut self, id: usize, lr: f32) -> Result<(), RenderError> {
        let n = self.groups.len();
        let g = self.groups.get_mut(id).ok_or(RenderError::Length {
            what: "adam group id",
            expected: n,
            found: id,
        })?;
        g.lr = lr;
        Ok(())
    }

    /// Resizes a group (e.g. after densification): kept entries keep their
    /// moments, new ones start at zero.
    pub fn resize_group(&mut self, id: usize, len: usize) -> Result<(), RenderError> {
        let n = self.groups.len();
        let g = self.groups.get_mut(id).ok_or(RenderError::Length {
            what: "adam group id",
            expected: n,
            found: id,
        })?;
        g.m.resize(len, 0.0);
        g.v.resize(len, 0.0);
        Ok(())
    }

    /// Rebuilds a group after its parameters were reordered, cloned or
    /// pruned (densification): entry `j` of the new group takes the moments
    /// of old entry `sources[j]` (each entry is `stride` floats), or zero
    /// moments where `sources[j]` is `None` (a parameter that is new).
    pub fn remap_group(
        &mut self,
        id: usize,
        sources: &[Option<usize>],
        stride: usize,
    ) -> Result<(), RenderError> {
        let n = self.groups.len();
        let g = self.groups.get_mut(id).ok_or(RenderError::Length {
            what: "adam group id",
            expected: n,
            found: id,
        })?;
        let old = g.m.len() / stride.max(1);
        let (mut m, mut v) = (
            vec![0.0; sources.len() * stride],
            vec![0.0; sources.len() * stride],
        );
        for (j, src) in sources.iter().enumerate() {
            if let Some(i) = *src {
                if i >= old {
                    return Err(RenderError::Length {
                        what: "adam remap source",
                        expected: old,
                        found: i,
                    });
                }
                m[j * stride..(j + 1) * stride].copy_from_slice(&g.m[i * stride..(i + 1) * stride]);
                v[j * stride..(j + 1) * stride].copy_from_slice(&g.v[i * stride..(i + 1) * stride]);
            }
        }
        g.m = m;
        g.v = v;
        Ok(())
    }

    /// One Adam step of group `id` on `params` with gradients `grads`.
    pub fn step(
        &mut self,
        id: usize,
        params: &mut [f32],
        grads: &[f32],
    ) -> Result<(), RenderError> {
        let (b1, b2, eps) = (self.beta1, self.beta2, self.eps);
        let n = self.groups.len();
        let g = self.groups.get_mut(id).ok_or(RenderError::Length {
            what: "adam group id",
            expected: n,
            found: id,
        })?;
        if params.len() != g.m.len() {
            return Err(RenderError::Length {
                what: "adam params",
                expected: g.m.len(),
                found: params.len(),
            });
        }
        if grads.len() != g.m.len() {
            return Err(RenderError::Length {
                what: "adam grads",
                expected: g.m.len(),
                found: grads.len(),
            });
        }
        if let Some(i) = grads.iter().position(|v| !v.is_finite()) {
            return Err(RenderError::NonFinite {
                what: "adam grads",
                index: i,
            });
        }
        g.t += 1;
        let bc1 = 1.0 - b1.powi(g.t as i32);
        let bc2 = 1.0 - b2.powi(g.t as i32);
        let lr = g.lr;
        for i in 0..params.len() {
            let gr = grads[i];
            g.m[i] = b1 * g.m[i] + (1.0 - b1) * gr;
            g.v[i] = b2 * g.v[i] + (1.0 - b2) * gr * gr;
            let mh = g.m[i] / bc1;
            let vh = g.v[i] / bc2;
            params[i] -= lr * mh / (vh.sqrt() + eps);
        }
        Ok(())
    }
}

/// Views a slice of glam vectors as flat floats (for [`Adam::step`]).
pub fn flat_vec3(v: &[glam::Vec3]) -> Vec<f32> {
    v.iter().flat_map(|p| p.to_array()).collect()
}

/// Writes flat floats back into glam vectors.
pub fn unflat_vec3(flat: &[f32], out: &mut [glam::Vec3]) {
    for (o, c) in out.iter_mut().zip(flat.chunks_exact(3)) {
        *o = glam::Vec3::new(c[0], c[1], c[2]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn minimises_a_quadratic_with_group_learning_rates() {
        // f(x) = sum (x_i - i)^2 in two groups with different rates.
        let mut adam = Adam::new(0.9, 0.999, 1e-8);
        let fast = adam.add_group("fast", 0.1, 3);
        let slow = adam.add_group("slow", 0.001, 3);
        let mut a = vec![0.0f32; 3];
        let mut b = vec![0.0f32; 3];
        for _ in 0..500 {
            let ga: Vec<f32> = a
                .iter()
                .enumerate()
                .map(|(i, x)| 2.0 * (x - i as f32))
                .collect();
            let gb: Vec<f32> = b
                .iter()
                .enumerate()
                .map(|(i, x)| 2.0 * (x - i as f32))
                .collect();
            adam.step(fast, &mut a, &ga).unwrap();
            adam.step(slow, &mut b, &gb).unwrap();
        }
        for i in 0..3 {
            assert!((a[i] - i as f32).abs() < 0.05, "{a:?}");
        }
        // The slow group moves at most lr per step.
        assert!((b[2] - 0.0).abs() <= 0.5 + 1e-4 && b[2] > 0.3, "{b:?}");
        assert_eq!(adam.group(fast).unwrap().steps(), 500);
        assert!(adam.step(fast, &mut a, &[0.0; 2]).is_err());
        assert!(adam.step(7, &mut a, &[0.0; 3]).is_err());
    }

    #[test]
    fn remap_keeps_the_moments_of_kept_entries_and_zeroes_new_ones() {
        let mut adam = Adam::default();
        let id = adam.add_group("p", 0.1, 6);
        let mut p = vec![0.0f32; 6];
        adam.step(id, &mut p, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
            .unwrap();
        let before = adam.group(id).unwrap().clone();
        // Stride 2: entries 0, 1, 2 -> [2, new, 0].
        adam.remap_group(id, &[Some(2), None, Some(0)], 2).unwrap();
        let after = adam.group(id).unwrap();
        assert_eq!(after.len(), 6);
        assert_eq!(&after.m[0..2], &before.m[4..6]);
        assert_eq!(&after.m[2..4], &[0.0, 0.0]);
        assert_eq!(&after.v[4..6], &before.v[0..2]);
        assert!(adam.remap_group(id, &[Some(3)], 2).is_err());
    }
}
