//! Small dense symmetric linear algebra for the calibration: cyclic Jacobi
//! eigen-decomposition and Cholesky solves of `P×P` normal matrices.
//!
//! Written for any `const P` (nalgebra's `SymmetricEigen` needs typenum
//! bounds that a generic `Const<P>` cannot name). Fixed memory, no
//! allocation; Jacobi is slow for large matrices but exact to rounding for
//! the 5-12 parameters of one sensor.

use nalgebra::{SMatrix, SVector};

use crate::Real;

/// Eigenvalues (unsorted) and eigenvectors (columns) of the symmetric
/// matrix `a` by cyclic Jacobi rotations.
pub(crate) fn sym_eigen<T: Real, const P: usize>(
    a: &SMatrix<T, P, P>,
) -> (SVector<T, P>, SMatrix<T, P, P>) {
    let mut a = *a;
    let mut v = SMatrix::<T, P, P>::identity();
    let eps = T::default_epsilon();
    for _sweep in 0..64 {
        let mut off = T::zero();
        let mut diag = T::zero();
        for i in 0..P {
            diag += a[(i, i)] * a[(i, i)];
            for j in (i + 1)..P {
                off += a[(i, j)] * a[(i, j)];
            }
        }
        if !(off > eps * eps * diag) {
            break;
        }
        for p in 0..P {
            for q in (p + 1)..P {
                let apq = a[(p, q)];
                if apq == T::zero() {
                    continue;
                }
                let theta = (a[(q, q)] - a[(p, p)]) / (T::lit(2.0) * apq);
                let t = if theta.abs() > T::lit(1e15) {
                    T::one() / (T::lit(2.0) * theta)
                } else {
                    let sgn = if theta < T::zero() {
                        -T::one()
                    } else {
                        T::one()
                    };
                    sgn / (theta.abs() + (theta * theta + T::one()).sqrt())
                };
                let c = T::one() / (t * t + T::one()).sqrt();
                let s = t * c;
                for k in 0..P {
                    let (akp, akq) = (a[(k, p)], a[(k, q)]);
                    a[(k, p)] = c * akp - s * akq;
                    a[(k, q)] = s * akp + c * akq;
                }
                for k in 0..P {
                    let (apk, aqk) = (a[(p, k)], a[(q, k)]);
                    a[(p, k)] = c * apk - s * aqk;
                    a[(q, k)] = s * apk + c * aqk;
                }
                for k in 0..P {
                    let (vkp, vkq) = (v[(k, p)], v[(k, q)]);
                    v[(k, p)] = c * vkp - s * vkq;
                    v[(k, q)] = s * vkp + c * vkq;
                }
            }
        }
    }
    (SVector::<T, P>::from_fn(|i, _| a[(i, i)]), v)
}

/// Cholesky factor `L` (lower) of a symmetric positive definite matrix, or
/// `None` when a pivot is not positive (singular or indefinite).
pub(crate) fn cholesky<T: Real, const P: usize>(a: &SMatrix<T, P, P>) -> Option<SMatrix<T, P, P>> {
    let mut l = SMatrix::<T, P, P>::zeros();
    for j in 0..P {
        let mut s = a[(j, j)];
        for k in 0..j {
            s -= l[(j, k)] * l[(j, k)];
        }
        if !(s > T::zero()) {
            return None;
        }
        let d = s.fast_sqrt();
        l[(j, j)] = d;
        for i in (j + 1)..P {
            let mut s = a[(i, j)];
            for k in 0..j {
                s -= l[(i, k)] * l[(j, k)];
            }
            l[(i, j)] = s / d;
        }
    }
    Some(l)
}

/// Solves `L Lᵀ x = b` given the Cholesky factor `L`.
pub(crate) fn cholesky_solve<T: Real, const P: usize>(
    l: &SMatrix<T, P, P>,
    b: &SVector<T, P>,
) -> SVector<T, P> {
    let mut y = *b;
    for i in 0..P {
        let mut s = y[i];
        for k in 0..i {
            s -= l[(i, k)] * y[k];
        }
        y[i] = s / l[(i, i)];
    }
    for i in (0..P).rev() {
        let mut s = y[i];
        for k in (i + 1)..P {
            s -= l[(k, i)] * y[k];
        }
        y[i] = s / l[(i, i)];
    }
    y
}

/// Inverse of a symmetric positive definite matrix from its Cholesky factor.
pub(crate) fn cholesky_inverse<T: Real, const P: usize>(l: &SMatrix<T, P, P>) -> SMatrix<T, P, P> {
    let mut inv = SMatrix::<T, P, P>::zeros();
    for j in 0..P {
        let mut e = SVector::<T, P>::zeros();
        e[j] = T::one();
        let col = cholesky_solve(l, &e);
        inv.set_column(j, &col);
    }
    // Symmetrise against rounding.
    (inv + inv.transpose()) * T::lit(0.5)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn test_matrix() -> SMatrix<f64, 5, 5> {
        let b = SMatrix::<f64, 5, 5>::from_fn(|i, j| {
            ((i * 7 + j * 3) % 11) as f64 - 4.0 + 0.1 * j as f64
        });
        b * b.transpose() + SMatrix::identity() * 0.5
    }

    #[test]
    fn jacobi_matches_nalgebra() {
        let a = test_matrix();
        let (w, v) = sym_eigen(&a);
        // A v_i = w_i v_i and V orthonormal
        for i in 0..5 {
            let vi = v.column(i).into_owned();
            assert_relative_eq!(a * vi, vi * w[i], epsilon = 1e-9);
        }
        assert_relative_eq!(v.transpose() * v, SMatrix::identity(), epsilon = 1e-12);
        let mut ours: Vec<f64> = w.iter().copied().collect();
        ours.sort_by(|x, y| x.partial_cmp(y).unwrap());
        let mut theirs: Vec<f64> = a.symmetric_eigen().eigenvalues.iter().copied().collect();
        theirs.sort_by(|x, y| x.partial_cmp(y).unwrap());
        for (x, y) in ours.iter().zip(theirs.iter()) {
            assert_relative_eq!(x, y, max_relative = 1e-10);
        }
    }

    #[test]
    fn cholesky_inverse_is_inverse() {
        let a = test_matrix();
        let l = cholesky(&a).unwrap();
        assert_relative_eq!(l * l.transpose(), a, epsilon = 1e-9);
        let inv = cholesky_inverse(&l);
        assert_relative_eq!(a * inv, SMatrix::identity(), epsilon = 1e-9);
        let b = SVector::<f64, 5>::from([1.0, -2.0, 0.5, 3.0, 0.0]);
        assert_relative_eq!(a * cholesky_solve(&l, &b), b, epsilon = 1e-9);
    }

    #[test]
    fn cholesky_rejects_singular() {
        let mut a = SMatrix::<f64, 3, 3>::identity();
        a[(2, 2)] = 0.0;
        assert!(cholesky(&a).is_none());
    }
}
