//! Symmetric positive-definite matrices of half-bandwidth 3 — a cubic B-spline's normal
//! matrix plus a second-difference penalty — factored, solved and inverted in band storage.
//!
//! Written here because nalgebra factors and inverts only dense matrices: O(n³) at up to 80
//! spline coefficients was most of the thread tracer's fitting time (its smoothing search
//! fits each axis a dozen times), where the band needs O(n). No well-kept crate does a
//! banded Cholesky factorisation together with the selected inverse (the covariance's band,
//! all the spline's pointwise variance reads).

/// Entries kept either side of the diagonal.
pub(crate) const HALF_BANDWIDTH: usize = 3;

/// A lower band: `rows[i][k]` is the entry at row `i`, column `i − k` (`k > i` unused).
pub(crate) type LowerBand = Vec<[f64; HALF_BANDWIDTH + 1]>;

/// The Cholesky factor L (A = L Lᵀ) of a band matrix, in band storage.
pub(crate) struct BandCholesky {
    l: LowerBand,
}

impl BandCholesky {
    /// Factors the matrix whose lower band is `a`; `None` when it is not positive definite.
    pub(crate) fn factor(mut a: LowerBand) -> Option<Self> {
        for i in 0..a.len() {
            // Left to right along the row: each entry needs those before it in its row and
            // the rows above.
            for k in (0..=HALF_BANDWIDTH.min(i)).rev() {
                let j = i - k;
                let mut s = a[i][k];
                for m in i.saturating_sub(HALF_BANDWIDTH)..j {
                    s -= a[i][i - m] * a[j][j - m];
                }
                if k == 0 {
                    // (Not above 0, NaN included.)
                    if s.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                        return None;
                    }
                    a[i][0] = s.sqrt();
                } else {
                    a[i][k] = s / a[j][0];
                }
            }
        }
        Some(Self { l: a })
    }

    /// x with A x = b.
    pub(crate) fn solve(&self, b: &[f64]) -> Vec<f64> {
        let l = &self.l;
        let n = l.len();
        let mut x = b.to_vec();
        for i in 0..n {
            let mut s = x[i];
            for k in 1..=HALF_BANDWIDTH.min(i) {
                s -= l[i][k] * x[i - k];
            }
            x[i] = s / l[i][0];
        }
        for i in (0..n).rev() {
            let mut s = x[i];
            for k in 1..=HALF_BANDWIDTH.min(n - 1 - i) {
                s -= l[i + k][k] * x[i + k];
            }
            x[i] = s / l[i][0];
        }
        x
    }

    /// The band of A⁻¹ (the same shape as A's): Takahashi's recursion from the last row up,
    /// Σᵢⱼ = δᵢⱼ / Lᵢᵢ² − Σₖ Lₖᵢ Σₖⱼ / Lᵢᵢ over k = i + 1 … i + 3, which reads only entries
    /// of Σ inside the band.
    pub(crate) fn inverse_band(&self) -> LowerBand {
        let l = &self.l;
        let n = l.len();
        let mut s: LowerBand = vec![[0.0; HALF_BANDWIDTH + 1]; n];
        let get = |s: &LowerBand, r: usize, c: usize| {
            let (hi, lo) = (r.max(c), r.min(c));
            s[hi][hi - lo]
        };
        for i in (0..n).rev() {
            let last = (i + HALF_BANDWIDTH).min(n - 1);
            for j in (i..=last).rev() {
                let mut v = if i == j { 1.0 / l[i][0] } else { 0.0 };
                for k in i + 1..=last {
                    v -= l[k][k - i] * get(&s, k, j);
                }
                s[j][j - i] = v / l[i][0];
            }
        }
        s
    }
}

/// The entry at (`r`, `c`) of a symmetric band matrix stored as its lower band (0 outside
/// the band).
pub(crate) fn at(band: &LowerBand, r: usize, c: usize) -> f64 {
    let (hi, lo) = (r.max(c), r.min(c));
    if hi - lo > HALF_BANDWIDTH {
        0.0
    } else {
        band[hi][hi - lo]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};
    use proptest::prelude::*;

    fn dense(a: &LowerBand) -> DMatrix<f64> {
        let n = a.len();
        DMatrix::from_fn(n, n, |r, c| at(a, r, c))
    }

    /// Positive-definite band matrices as the spline fit builds them: a sum of outer
    /// products of four adjacent weights, plus a second-difference penalty.
    fn normal_matrix() -> impl Strategy<Value = LowerBand> {
        (4usize..40)
            .prop_flat_map(|n| {
                (
                    Just(n),
                    prop::collection::vec((0.0f64..1.0, 0.01f64..100.0), 0..120),
                    0.0f64..1e3,
                )
            })
            .prop_map(|(n, obs, smoothing)| {
                let mut a: LowerBand = vec![[0.0; 4]; n];
                let mut add = |r: usize, c: usize, v: f64| {
                    let (hi, lo) = (r.max(c), r.min(c));
                    a[hi][hi - lo] += v;
                };
                for (t, wt) in obs {
                    let i = ((t * (n - 3) as f64) as usize).min(n - 4);
                    let u = t * (n - 3) as f64 - i as f64;
                    let w = [
                        (1.0 - u).powi(3) / 6.0,
                        (3.0 * u.powi(3) - 6.0 * u * u + 4.0) / 6.0,
                        (-3.0 * u.powi(3) + 3.0 * u * u + 3.0 * u + 1.0) / 6.0,
                        u.powi(3) / 6.0,
                    ];
                    for p in 0..4 {
                        for q in 0..=p {
                            add(i + p, i + q, wt * w[p] * w[q]);
                        }
                    }
                }
                let d = [1.0, -2.0, 1.0];
                for k in 0..n - 2 {
                    for p in 0..3 {
                        for q in 0..=p {
                            add(k + p, k + q, smoothing * d[p] * d[q]);
                        }
                    }
                }
                // A ridge, so every draw is positive definite and conditioned well enough
                // (at most about 10⁵) for the two factorisations to agree to 1e-7.
                for row in &mut a {
                    row[0] += 1.0;
                }
                a
            })
    }

    proptest! {
        #[test]
        fn the_band_solves_and_inverts_as_the_dense_matrix_does(
            a in normal_matrix(),
            seed in 0u64..1000,
        ) {
            let n = a.len();
            let d = dense(&a);
            let chol = BandCholesky::factor(a).expect("positive definite");
            let b: Vec<f64> = (0..n).map(|i| ((i as u64 * 7919 + seed) % 101) as f64 - 50.0).collect();
            let x = chol.solve(&b);
            let dense_x = d.clone().cholesky().expect("positive definite").solve(&DVector::from_vec(b));
            let scale = dense_x.amax().max(1.0);
            for i in 0..n {
                prop_assert!((x[i] - dense_x[i]).abs() <= 1e-7 * scale, "x[{i}] {} against {}", x[i], dense_x[i]);
            }
            let inv = chol.inverse_band();
            let dense_inv = d.try_inverse().expect("invertible");
            let scale = dense_inv.amax().max(1e-12);
            for r in 0..n {
                for c in r.saturating_sub(HALF_BANDWIDTH)..=r {
                    prop_assert!(
                        (at(&inv, r, c) - dense_inv[(r, c)]).abs() <= 1e-7 * scale,
                        "Σ[{r},{c}] {} against {}", at(&inv, r, c), dense_inv[(r, c)]
                    );
                }
            }
        }
    }

    #[test]
    fn a_matrix_that_is_not_positive_definite_is_refused() {
        let mut a: LowerBand = vec![[0.0; 4]; 5];
        for row in &mut a {
            row[0] = 1.0;
        }
        a[3][0] = -1.0;
        assert!(BandCholesky::factor(a.clone()).is_none());
        a[3][0] = f64::NAN;
        assert!(BandCholesky::factor(a).is_none());
        // The identity is its own factor and inverse.
        let eye: LowerBand = vec![[1.0, 0.0, 0.0, 0.0]; 6];
        let chol = BandCholesky::factor(eye.clone()).expect("the identity");
        assert_eq!(
            chol.solve(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
            vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
        );
        assert_eq!(chol.inverse_band(), eye);
    }
}
