//! Device buffers kept between calls.
//!
//! A learner renders and differentiates the same scene size every iteration,
//! so allocating every buffer anew per call (the first port did) pays the
//! driver's allocation and wgpu's zero-fill for nothing. The pool hands out a
//! free buffer of the same usage and size class, and takes it back when the
//! [`Pooled`] guard drops (after the backward pass has used the render
//! state's buffers).
//!
//! Sizes are rounded up to classes 1/16 of a power of two apart, so a scene
//! whose instance count drifts a little between iterations reuses its
//! buffers (at most 12.5 % of a buffer is slack). The free list is bounded
//! ([`MAX_FREE_BYTES`], oldest dropped first), so a run that changes sizes
//! does not hold every size it has seen.
//!
//! Invariant: a pooled buffer holds the previous user's bytes, so no kernel
//! may read bytes that this call did not write. The kernels write every
//! splat, offset, image value and gradient record they later read; the
//! callers in `mod.rs` clear what is only partly written (the tile ranges,
//! the per-instance gradient records) and the offsets. The crate's tests
//! check it: there every buffer handed out is poisoned first ([`Pool::take`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Bytes the free list may hold before the oldest buffers are dropped.
const MAX_FREE_BYTES: u64 = 4 << 30;

/// The size class of a request: `bytes` rounded up to a multiple of a
/// sixteenth of its power of two (and at least 256 bytes, a multiple of 4).
pub(super) fn size_class(bytes: u64) -> u64 {
    let b = bytes.max(256);
    let step = (b.next_power_of_two() / 16).max(256);
    b.next_multiple_of(step)
}

/// Free buffers, oldest first.
#[derive(Debug, Default)]
pub(super) struct Pool {
    free: Mutex<Vec<wgpu::Buffer>>,
    /// Buffers created so far (reuse shows as this not growing).
    created: AtomicU64,
}

impl Pool {
    /// A buffer of `usage` with at least `bytes` bytes (its size is
    /// [`size_class`]`(bytes)`); its contents are unspecified.
    ///
    /// In the crate's tests every storage buffer handed out is first filled
    /// with 0xFF bytes (NaN as f32, `u32::MAX` as u32) through `queue`, so a
    /// kernel that reads bytes nobody wrote changes the results the tests
    /// compare (the module invariant).
    pub(super) fn take(
        self: &Arc<Self>,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        label: &str,
        usage: wgpu::BufferUsages,
        bytes: u64,
    ) -> Pooled {
        let size = size_class(bytes);
        let found = {
            let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
            free.iter()
                .position(|b| b.size() == size && b.usage() == usage)
                .map(|i| free.remove(i))
        };
        let buf = found.unwrap_or_else(|| {
            self.created.fetch_add(1, Ordering::Relaxed);
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        });
        if cfg!(test) && usage.contains(wgpu::BufferUsages::STORAGE) {
            queue.write_buffer(&buf, 0, &vec![0xFF; size as usize]);
        }
        #[cfg(not(test))]
        let _ = queue;
        Pooled {
            buf: Some(buf),
            pool: Arc::clone(self),
        }
    }

    fn give_back(&self, buf: wgpu::Buffer) {
        let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        free.push(buf);
        let mut total: u64 = free.iter().map(|b| b.size()).sum();
        while total > MAX_FREE_BYTES && !free.is_empty() {
            total -= free.remove(0).size();
        }
    }

    /// Buffers created since the pool was made.
    pub(super) fn created(&self) -> u64 {
        self.created.load(Ordering::Relaxed)
    }
}

/// A buffer on loan from the [`Pool`]; returned to it on drop.
#[derive(Debug)]
pub(super) struct Pooled {
    buf: Option<wgpu::Buffer>,
    pool: Arc<Pool>,
}

impl std::ops::Deref for Pooled {
    type Target = wgpu::Buffer;
    fn deref(&self) -> &wgpu::Buffer {
        self.buf
            .as_ref()
            .expect("a pooled buffer is present until drop")
    }
}

impl Drop for Pooled {
    fn drop(&mut self) {
        if let Some(b) = self.buf.take() {
            self.pool.give_back(b);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::size_class;

    #[test]
    fn size_classes_round_up_by_at_most_a_sixteenth() {
        for bytes in [
            0u64,
            1,
            255,
            256,
            257,
            1000,
            4096,
            4097,
            1 << 20,
            (1 << 20) + 1,
            123_456_789,
        ] {
            let c = size_class(bytes);
            assert!(c >= bytes.max(256), "{bytes} -> {c}");
            assert_eq!(c % 4, 0, "{bytes} -> {c}");
            assert!(
                c as f64 <= (bytes.max(256) as f64) * 1.125 + 256.0,
                "{bytes} -> {c}"
            );
        }
        // Nearby sizes share a class: that is what makes reuse work.
        assert_eq!(size_class(1_000_000), size_class(1_010_000));
    }
}
