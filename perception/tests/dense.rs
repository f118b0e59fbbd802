//! Dense matching on any input a user can give it: any image size, region and disparity
//! range, along any paths, with any left-right check, filtered or not, answers a map or a
//! configuration error with the reason; it never panics.

use proptest::prelude::*;
use stitch_perception::{LeftRight, PerceptionError, Rect, SemiGlobalMatcher, SgmPaths};
use stitch_robot::RgbImage;

fn image(w: u32, h: u32, seed: u64) -> RgbImage {
    let mut img = RgbImage::new(w, h);
    let mut state = seed | 1;
    for v in &mut img.data {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        *v = (state >> 24) as u8;
    }
    img
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(
        std::env::var("STITCH_PROPTEST_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(300)
    ))]

    #[test]
    fn any_region_and_range_gives_a_map_or_a_reason(
        w in 1u32..40, h in 1u32..24, (a, b, c, e) in (any::<u32>(), any::<u32>(), any::<u32>(), any::<u32>()),
        lo in 0u32..30, span in 0u32..60, paths in 0usize..3, left_right in 0usize..3,
        parallel: bool, median: bool, seed: u64, other_size in proptest::bool::weighted(0.1),
    ) {
        let left = image(w, h, seed);
        let right = if other_size { image(w + 1, h, !seed) } else { image(w, h, !seed) };
        let m = SemiGlobalMatcher {
            around_mask_px: None,
            paths: [SgmPaths::Four, SgmPaths::Five, SgmPaths::Eight][paths],
            left_right: [LeftRight::Nearest, LeftRight::Between, LeftRight::Winners][left_right],
            median,
            ..SemiGlobalMatcher::default()
        };
        // Mostly inside the image, now and then past its edge or empty.
        let (x0, y0) = (a % (w + 1), c % (h + 1));
        let roi = Rect { x0, y0, x1: x0 + b % (w - x0 + 2), y1: y0 + e % (h - y0 + 2) };
        let lo = lo % (w + 3);
        match m.dense(&left, &right, roi, lo, lo + span, parallel) {
            Ok(map) => {
                prop_assert_eq!(map.roi, roi);
                prop_assert_eq!(map.data.len(), (roi.width() * roi.height()) as usize);
                for d in map.data.iter().filter(|d| d.is_finite()) {
                    prop_assert!(*d >= lo as f32 - 0.5 && *d <= (lo + span) as f32 + 0.5, "{d}");
                }
            }
            Err(PerceptionError::Config { message }) => prop_assert!(!message.is_empty()),
            Err(e) => prop_assert!(false, "not a configuration error: {e}"),
        }
    }
}
