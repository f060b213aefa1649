//! The one tolerance type of every kernel-versus-reference comparison:
//! `|actual − expected| ≤ abs + rel·|expected|`, element by element.

/// Relative and absolute parts of a tolerance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tolerance {
    pub rel: f32,
    pub abs: f32,
}

/// The first element outside a tolerance.
#[derive(Debug, Clone, PartialEq)]
pub struct Mismatch {
    pub index: usize,
    pub actual: f32,
    pub expected: f32,
    /// How many elements were outside.
    pub count: usize,
}

impl std::fmt::Display for Mismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} elements outside tolerance; first at {}: got {}, expected {}",
            self.count, self.index, self.actual, self.expected
        )
    }
}

impl Tolerance {
    /// f32 kernels against an f64 or f32 reference (the 1e-4 relative).
    pub const F32: Tolerance = Tolerance {
        rel: 1e-4,
        abs: 1e-6,
    };

    pub fn accepts(&self, actual: f32, expected: f32) -> bool {
        (actual - expected).abs() <= self.abs + self.rel * expected.abs()
    }

    /// Compares element by element; lengths must match.
    pub fn check(&self, actual: &[f32], expected: &[f32]) -> Result<(), Mismatch> {
        assert_eq!(
            actual.len(),
            expected.len(),
            "compared slices differ in length"
        );
        let mut first: Option<Mismatch> = None;
        for (i, (&a, &e)) in actual.iter().zip(expected).enumerate() {
            if !self.accepts(a, e) {
                match &mut first {
                    Some(m) => m.count += 1,
                    None => {
                        first = Some(Mismatch {
                            index: i,
                            actual: a,
                            expected: e,
                            count: 1,
                        })
                    }
                }
            }
        }
        first.map_or(Ok(()), Err)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_and_absolute_parts() {
        let t = Tolerance {
            rel: 1e-3,
            abs: 1e-6,
        };
        assert!(t.accepts(1000.5, 1000.0));
        assert!(!t.accepts(1001.5, 1000.0));
        assert!(t.accepts(5e-7, 0.0));
        assert!(!t.accepts(f32::NAN, 0.0));
        let m = t
            .check(&[1.0, 2.0, 9.0, 9.0], &[1.0, 2.0, 3.0, 4.0])
            .unwrap_err();
        assert_eq!((m.index, m.count), (2, 2));
    }
}
