//! Size limits on what files, scripts and flags may ask for: each limit
//! lives here once, and every reader checks against it, so that the same
//! image is not accepted by one reader and refused by another.

/// The most pixels an image may have, decoded from a file or rendered:
/// 8192² (as RGBA f32, 1 GiB). Captures are far smaller (LLFF full
/// resolution is 4032×3024).
pub const MAX_IMAGE_PIXELS: u64 = 1 << 26;

/// The longest image side a camera may describe (camera files, COLMAP,
/// LLFF, orbits, training images); the pixel count is bounded by
/// [`MAX_IMAGE_PIXELS`] as well. 65535: the trainer stores pixel
/// coordinates in 16 bits.
pub const MAX_IMAGE_SIDE: u32 = u16::MAX as u32;

/// The longest side of an image the GPU draws into (a window, a headless
/// render target): the texture size every wgpu adapter supports.
pub const MAX_TEXTURE_SIDE: u32 = 8192;

/// Whether a `width`×`height` image is within [`MAX_IMAGE_SIDE`] and
/// [`MAX_IMAGE_PIXELS`] (and not empty).
pub fn image_size_ok(width: u32, height: u32) -> bool {
    let side = 1..=MAX_IMAGE_SIDE;
    side.contains(&width) && side.contains(&height) && u64::from(width) * u64::from(height) <= MAX_IMAGE_PIXELS
}

/// Whether the GPU can draw a `width`×`height` image.
pub fn texture_size_ok(width: u32, height: u32) -> bool {
    let side = 1..=MAX_TEXTURE_SIDE;
    side.contains(&width) && side.contains(&height)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_sizes_are_bounded_by_side_and_by_pixels() {
        assert!(image_size_ok(8192, 8192) && image_size_ok(65535, 1));
        assert!(!image_size_ok(0, 10) && !image_size_ok(65536, 1) && !image_size_ok(8193, 8192));
        assert!(texture_size_ok(8192, 1) && !texture_size_ok(8193, 1));
    }
}
