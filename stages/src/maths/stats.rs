//! Statistics the stages share: percentiles (NumPy's default `linear`
//! method), the PSNR of two images, standard normal samples and the standard
//! normal CDF.

use rand::Rng;

use crate::data::image::ImageF32;

/// A standard normal sample (Box-Muller) from a seeded generator.
pub fn standard_normal(rng: &mut impl Rng) -> f32 {
    let u1: f32 = rng.gen::<f32>().max(1e-12);
    let u2: f32 = rng.gen();
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

/// The `q`-th percentile (`q` in [0, 100]) by linear interpolation between
/// order statistics; `None` for an empty slice. NaNs must have been rejected
/// by the caller.
pub fn percentile(values: &[f32], q: f64) -> Option<f32> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f32::total_cmp);
    Some(percentile_sorted(&v, q))
}

/// [`percentile`] on values sorted ascending (non-empty).
pub fn percentile_sorted(sorted: &[f32], q: f64) -> f32 {
    let n = sorted.len();
    if n == 1 {
        return sorted[0];
    }
    let pos = (q.clamp(0.0, 100.0) / 100.0) * (n - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(n - 1);
    let frac = pos - lo as f64;
    (sorted[lo] as f64 + frac * (sorted[hi] as f64 - sorted[lo] as f64)) as f32
}

/// PSNR in dB of two images of the same shape with values in [0, 1] (all
/// channels); infinity when identical.
pub fn psnr(a: &ImageF32, b: &ImageF32) -> f32 {
    let se: f64 = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| {
            let d = (*x - *y) as f64;
            d * d
        })
        .sum();
    let mse = se / a.data.len().max(1) as f64;
    if mse <= 0.0 {
        f32::INFINITY
    } else {
        (10.0 * (1.0 / mse).log10()) as f32
    }
}

/// The standard normal CDF `Phi(x)`, from Abramowitz and Stegun's erf
/// approximation 7.1.26 (absolute error below 1.5e-7): no special-function crate
/// for one smooth step.
pub fn normal_cdf(x: f32) -> f32 {
    let z = x.abs() / std::f32::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * z);
    let poly = t
        * (0.254_829_6
            + t * (-0.284_496_74 + t * (1.421_413_7 + t * (-1.453_152 + t * 1.061_405_4))));
    let erf = 1.0 - poly * (-z * z).exp();
    if x >= 0.0 {
        0.5 * (1.0 + erf)
    } else {
        0.5 * (1.0 - erf)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentile_interpolates_like_numpy() {
        let v = [4.0, 1.0, 3.0, 2.0];
        assert_eq!(percentile(&v, 0.0), Some(1.0));
        assert_eq!(percentile(&v, 100.0), Some(4.0));
        // numpy.percentile([1,2,3,4], 75) == 3.25
        assert!((percentile(&v, 75.0).unwrap() - 3.25).abs() < 1e-6);
        assert_eq!(percentile(&[], 50.0), None);
    }

    #[test]
    fn normal_cdf_matches_known_values() {
        // Phi(0) = 0.5, Phi(1) = 0.841344746, Phi(-1.96) = 0.024997895, Phi(3) = 0.998650102.
        for (x, want) in [
            (0.0, 0.5),
            (1.0, 0.841_344_7),
            (-1.96, 0.024_997_9),
            (3.0, 0.998_650_1),
        ] {
            assert!(
                (normal_cdf(x) - want).abs() < 1e-6,
                "Phi({x}) = {}",
                normal_cdf(x)
            );
        }
    }
}
