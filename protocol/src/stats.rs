//! Small measuring helpers both ends' reports use (the server's `bench`, the viewer's
//! stats and `--bench`, the load generator).

/// The `q`-quantile (0..=1) of `values` by the nearest-rank method; 0 when empty.
pub fn quantile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let rank = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len());
    v[rank - 1]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles() {
        for (values, q, want) in [
            (vec![], 0.5, 0.0),
            (vec![3.0], 0.5, 3.0),
            (vec![5.0, 1.0, 3.0], 0.5, 3.0),
            (vec![4.0, 1.0, 3.0, 2.0], 0.5, 2.0),
            ((1..=100).map(f64::from).collect(), 0.99, 99.0),
            ((1..=100).map(f64::from).collect(), 1.0, 100.0),
        ] {
            assert_eq!(quantile(&values, q), want, "{values:?} q {q}");
        }
    }
}
