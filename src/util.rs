//! Small shared helpers.

/// SplitMix64: a tiny, fast, well-distributed deterministic generator. Used
/// where results must be reproducible from a seed (k-means++ picks, demo
/// noise, random test fields) without pulling a crate into the library.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform integer in [0, n).
    pub fn below(&mut self, n: usize) -> usize {
        (self.unit() * n as f64) as usize % n.max(1)
    }
    /// A uniformly chosen element (`items` must not be empty).
    pub fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len())]
    }
}

/// Milliseconds elapsed since `t`.
pub fn ms_since(t: std::time::Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// How far a long operation has come, shared between the thread doing it
/// and a UI showing it (the editor's progress bar). Cheap to clone; setting
/// it takes a short lock, so callers report per frame, stroke or step, not
/// per voxel.
#[derive(Clone, Debug, Default)]
pub struct Progress(std::sync::Arc<std::sync::Mutex<Option<ProgressState>>>);

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ProgressState {
    pub stage: String,
    pub done: u64,
    /// 0 when the amount of work is not known in advance.
    pub total: u64,
}

impl ProgressState {
    /// Share done in [0, 1], when the total is known.
    pub fn fraction(&self) -> Option<f32> {
        (self.total > 0).then(|| (self.done as f64 / self.total as f64).min(1.0) as f32)
    }
}

impl Progress {
    pub fn set(&self, stage: &str, done: u64, total: u64) {
        if let Ok(mut s) = self.0.lock() {
            *s = Some(ProgressState {
                stage: stage.to_string(),
                done,
                total,
            });
        }
    }
    pub fn clear(&self) {
        if let Ok(mut s) = self.0.lock() {
            *s = None;
        }
    }
    pub fn get(&self) -> Option<ProgressState> {
        self.0.lock().ok().and_then(|s| s.clone())
    }
}

/// A byte count for people: "812 KB", "3.4 MB", "2.0 GB" (powers of 1024).
pub fn human_bytes(n: usize) -> String {
    let n = n as f64;
    if n < 1024.0 * 1024.0 {
        format!("{:.0} KB", n / 1024.0)
    } else if n < 1024.0 * 1024.0 * 1024.0 {
        format!("{:.1} MB", n / (1024.0 * 1024.0))
    } else {
        format!("{:.1} GB", n / (1024.0 * 1024.0 * 1024.0))
    }
}

/// A path's extension, lower-cased ("" when it has none): the one rule by
/// which file kinds are told apart (scripts, compositions, meshes, images).
pub fn extension(path: &std::path::Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default()
}

/// The smallest |determinant| of an invertible transform's linear part: the
/// one threshold for every transform read or built (composition documents,
/// script transforms, render layers, mesh export).
pub const MIN_DETERMINANT: f32 = 1e-12;

/// Whether `a` is finite and invertible (see [`MIN_DETERMINANT`]).
pub fn invertible(a: &glam::Affine3A) -> bool {
    let det = a.matrix3.determinant();
    det.is_finite() && det.abs() > MIN_DETERMINANT && a.translation.is_finite()
}

/// An affine map from a row-major 4×4 matrix (JSON `transform_matrix`,
/// composition transforms, script `matrix`). The bottom row is ignored.
pub fn affine_from_rows(m: &[[f32; 4]; 4]) -> glam::Affine3A {
    glam::Affine3A::from_mat4(glam::Mat4::from_cols_array_2d(m).transpose())
}

/// The row-major 4×4 matrix of an affine map.
pub fn affine_to_rows(a: &glam::Affine3A) -> [[f32; 4]; 4] {
    let m = glam::Mat4::from(*a).transpose();
    [
        m.x_axis.to_array(),
        m.y_axis.to_array(),
        m.z_axis.to_array(),
        m.w_axis.to_array(),
    ]
}

/// Serde for an affine map stored as a row-major 4×4 matrix
/// (`#[serde(with = "crate::util::rows")]`). Reading checks nothing: the
/// reader of the document says what is wrong with which transform.
pub mod rows {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(a: &glam::Affine3A, s: S) -> Result<S::Ok, S::Error> {
        super::affine_to_rows(a).serialize(s)
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<glam::Affine3A, D::Error> {
        Ok(super::affine_from_rows(&<[[f32; 4]; 4]>::deserialize(d)?))
    }
}

/// Asks the caches for the line holding `p` (a hint: it reads nothing,
/// cannot fault, and does nothing off x86-64).
#[inline(always)]
pub fn prefetch<T>(p: *const T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch is a hint; any address is allowed.
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(p as *const i8)
    };
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Whether this CPU runs AVX2 (checked once).
pub fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        static HAS: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        *HAS.get_or_init(|| std::is_x86_feature_detected!("avx2"))
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}
