//! Array helpers the stages share: an array's elements as one row-major slice, for hot
//! loops over plain slices.

/// The elements of `a` as one slice in logical (row-major) order: borrowed when the array
/// is in standard layout, copied once otherwise, so hot loops can run over plain slices.
pub(crate) fn contiguous<'a, T: Clone, D: ndarray::Dimension>(
    a: ndarray::ArrayView<'a, T, D>,
) -> std::borrow::Cow<'a, [T]> {
    match a.to_slice() {
        Some(s) => std::borrow::Cow::Borrowed(s),
        None => std::borrow::Cow::Owned(a.iter().cloned().collect()),
    }
}
