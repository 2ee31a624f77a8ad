//! The ground floor: the scalar type every numeric path is generic over. It knows no stage;
//! every stage may use it.

/// Floating-point type of a CPU path: f32 (the fast path, as on the GPU) or f64 (the
/// reference every fast path is checked against).
pub trait Real: nalgebra::RealField + Copy + Default + Send + Sync + 'static {
    fn of(x: f64) -> Self;
    fn to_f64(self) -> f64;
    /// Truncation to i32 and back: single instructions in hot loops, where the
    /// usize/u64 conversions are multi-instruction sequences.
    fn trunc_i32(self) -> i32;
    fn of_i32(i: i32) -> Self;
    fn of_f32(x: f32) -> Self;
    /// The slice itself where Self is f32: the hot loops' f32-only lanes take it.
    fn as_f32_mut(values: &mut [Self]) -> Option<&mut [f32]>;
}
impl Real for f32 {
    fn of(x: f64) -> Self {
        x as f32
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
    fn trunc_i32(self) -> i32 {
        self as i32
    }
    fn of_i32(i: i32) -> Self {
        i as f32
    }
    fn of_f32(x: f32) -> Self {
        x
    }
    fn as_f32_mut(values: &mut [Self]) -> Option<&mut [f32]> {
        Some(values)
    }
}
impl Real for f64 {
    fn of(x: f64) -> Self {
        x
    }
    fn to_f64(self) -> f64 {
        self
    }
    fn trunc_i32(self) -> i32 {
        self as i32
    }
    fn of_i32(i: i32) -> Self {
        i as f64
    }
    fn of_f32(x: f32) -> Self {
        x as f64
    }
    fn as_f32_mut(_: &mut [Self]) -> Option<&mut [f32]> {
        None
    }
}
