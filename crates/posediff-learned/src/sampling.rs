//! Bilinear sampling of a channel-major feature map at real-valued pixel positions, as
//! torchvision's `deform_conv2d` and `grid_sample(align_corners=True, padding_mode="zeros")`
//! do it: a neighbour outside the map contributes zero.

/// The four neighbours and weights of one sample position (`None` where it is outside).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Tap {
    idx: [usize; 4],
    w: [f32; 4],
}

impl Tap {
    /// The taps of pixel position `(x, y)` (column, row; pixel centres at integers) in a
    /// `width × height` map.
    pub(crate) fn new(x: f32, y: f32, width: usize, height: usize) -> Self {
        let (wf, hf) = (width as f32, height as f32);
        let mut tap = Tap {
            idx: [0; 4],
            w: [0.0; 4],
        };
        // torchvision's early exit; grid_sample gives the same zero (every weight meets an
        // outside neighbour or is zero there).
        if y <= -1.0 || hf <= y || x <= -1.0 || wf <= x {
            return tap;
        }
        let (y0, x0) = (y.floor(), x.floor());
        let (ly, lx) = (y - y0, x - x0);
        let (hy, hx) = (1.0 - ly, 1.0 - lx);
        let (y0, x0) = (y0 as i64, x0 as i64);
        let corners = [
            (y0, x0, hy * hx),
            (y0, x0 + 1, hy * lx),
            (y0 + 1, x0, ly * hx),
            (y0 + 1, x0 + 1, ly * lx),
        ];
        for (k, (yy, xx, w)) in corners.into_iter().enumerate() {
            if yy >= 0 && xx >= 0 && (yy as usize) < height && (xx as usize) < width {
                tap.idx[k] = yy as usize * width + xx as usize;
                tap.w[k] = w;
            }
        }
        tap
    }

    /// The neighbours with a non-zero weight: `(x, y, weight)` (the same sum as
    /// [`Tap::sample`], for values that are computed per pixel).
    pub(crate) fn corners(&self, width: usize) -> impl Iterator<Item = (usize, usize, f32)> + '_ {
        self.idx
            .iter()
            .zip(&self.w)
            .filter(|(_, w)| **w != 0.0)
            .map(move |(&i, &w)| (i % width, i / width, w))
    }

    /// The interpolated value of one channel plane (`width × height`, row-major).
    #[inline]
    pub(crate) fn sample(&self, plane: &[f32]) -> f32 {
        // The same order of operations as torchvision (w1·v1 + w2·v2 + w3·v3 + w4·v4).
        self.w[0] * plane[self.idx[0]]
            + self.w[1] * plane[self.idx[1]]
            + self.w[2] * plane[self.idx[2]]
            + self.w[3] * plane[self.idx[3]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolates_inside_and_zero_pads_outside() {
        // 3 × 2 map: value = 10·row + column.
        let plane = [0.0, 1.0, 2.0, 10.0, 11.0, 12.0];
        let at = |x, y| Tap::new(x, y, 3, 2).sample(&plane);
        assert_eq!(at(0.0, 0.0), 0.0);
        assert_eq!(at(2.0, 1.0), 12.0);
        assert!((at(0.5, 0.5) - 5.5).abs() < 1e-6);
        assert!((at(1.25, 0.0) - 1.25).abs() < 1e-6);
        // Half a pixel beyond the right edge: half of the edge value (the outside neighbour
        // is zero).
        assert!((at(2.5, 0.0) - 1.0).abs() < 1e-6);
        assert_eq!(at(-1.0, 0.0), 0.0);
        assert_eq!(at(0.0, 2.0), 0.0);
    }
}
