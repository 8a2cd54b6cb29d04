//! Order statistics shared by the builder and the checks.

/// The upper median (element `len / 2` in `f64::total_cmp` order), `None`
/// for no values.
pub(crate) fn median(mut values: Vec<f64>) -> Option<f64> {
    let mid = values.len() / 2;
    (!values.is_empty()).then(|| *values.select_nth_unstable_by(mid, f64::total_cmp).1)
}

#[cfg(test)]
mod tests {
    use super::median;

    #[test]
    fn the_median_is_the_upper_middle_value() {
        assert_eq!(median(vec![]), None);
        assert_eq!(median(vec![3.0]), Some(3.0));
        assert_eq!(median(vec![4.0, 1.0]), Some(4.0));
        assert_eq!(median(vec![5.0, -1.0, 2.0, 9.0, 0.5]), Some(2.0));
    }
}
