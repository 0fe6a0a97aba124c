//! A small z-buffer rasteriser for OpenCV cameras.
//!
//! Triangles are clipped against the near plane in camera coordinates, projected with `K`, and
//! filled at the pixel centres (integer coordinates, the OpenCV convention) by edge functions.
//! Attributes are interpolated perspective-correctly: the camera-space point of a pixel is
//! `Σ bᵢ pᵢ/zᵢ / Σ bᵢ/zᵢ` with screen-space barycentrics `bᵢ`, which is exactly where the
//! pixel's ray meets the triangle's plane. Every pixel therefore knows the world point it shows,
//! and that point projects back onto the pixel centre: the ground truth the tests check.

use nalgebra::Vector3;
use posediff_geometry::Camera;

/// A world-space triangle of one object.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Triangle {
    /// Vertices in world coordinates.
    pub v: [Vector3<f64>; 3],
    /// Which object (material) it belongs to.
    pub object: u32,
}

/// What a pixel shows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// The world point on the pixel's ray.
    pub world: Vector3<f64>,
    /// The triangle's unit normal in world coordinates, facing the camera.
    pub normal: Vector3<f64>,
    /// Its depth along the optical axis.
    pub depth: f64,
    /// The object.
    pub object: u32,
}

/// Per-pixel hits, row-major (`None`: background).
#[derive(Debug, Clone, PartialEq)]
pub struct Buffers {
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// `width × height` hits.
    pub hits: Vec<Option<Hit>>,
}

impl Buffers {
    /// The hit at pixel `(x, y)`.
    pub fn at(&self, x: usize, y: usize) -> Option<&Hit> {
        self.hits.get(y * self.width + x).and_then(Option::as_ref)
    }
}

/// Clips a camera-space triangle to `z ≥ near`: 0, 3 or 4 vertices.
fn clip_near(p: [Vector3<f64>; 3], near: f64) -> Vec<Vector3<f64>> {
    let mut out = Vec::with_capacity(4);
    for i in 0..3 {
        let (a, b) = (p[i], p[(i + 1) % 3]);
        let (ina, inb) = (a.z >= near, b.z >= near);
        if ina {
            out.push(a);
        }
        if ina != inb {
            let t = (near - a.z) / (b.z - a.z);
            out.push(a + (b - a) * t);
        }
    }
    out
}

fn edge(a: (f64, f64), b: (f64, f64), p: (f64, f64)) -> f64 {
    (b.0 - a.0) * (p.1 - a.1) - (b.1 - a.1) * (p.0 - a.0)
}

/// Rasterises `triangles` seen by `camera` (its image size), nearest surface per pixel.
pub fn rasterise(triangles: &[Triangle], camera: &Camera, near: f64) -> Buffers {
    let (w, h) = (
        camera.image_size.width() as usize,
        camera.image_size.height() as usize,
    );
    let mut hits: Vec<Option<Hit>> = vec![None; w * h];
    let r = camera.cam_from_world.rotation;
    let t = camera.cam_from_world.translation;
    let k = &camera.intrinsics;
    let (fx, fy, cx, cy) = (k.fx(), k.fy(), k.cx(), k.cy());
    let rt = r.transpose();
    for tri in triangles {
        let cam = tri.v.map(|v| r * v + t);
        let poly = clip_near(cam, near);
        if poly.len() < 3 {
            continue;
        }
        let mut normal = (tri.v[1] - tri.v[0]).cross(&(tri.v[2] - tri.v[0]));
        let len = normal.norm();
        if len <= 0.0 || !len.is_finite() {
            continue;
        }
        normal /= len;
        // Face the camera: the camera centre in world coordinates is −Rᵀt.
        let centre = -(rt * t);
        if normal.dot(&(centre - tri.v[0])) < 0.0 {
            normal = -normal;
        }
        for fan in 1..poly.len() - 1 {
            let p = [poly[0], poly[fan], poly[fan + 1]];
            let s = p.map(|q| (fx * q.x / q.z + cx, fy * q.y / q.z + cy));
            let area = edge(s[0], s[1], s[2]);
            if area.abs() < 1e-12 || !area.is_finite() {
                continue;
            }
            let min_x = s
                .iter()
                .map(|q| q.0)
                .fold(f64::INFINITY, f64::min)
                .ceil()
                .max(0.0);
            let max_x = s
                .iter()
                .map(|q| q.0)
                .fold(f64::NEG_INFINITY, f64::max)
                .floor()
                .min(w as f64 - 1.0);
            let min_y = s
                .iter()
                .map(|q| q.1)
                .fold(f64::INFINITY, f64::min)
                .ceil()
                .max(0.0);
            let max_y = s
                .iter()
                .map(|q| q.1)
                .fold(f64::NEG_INFINITY, f64::max)
                .floor()
                .min(h as f64 - 1.0);
            if min_x > max_x || min_y > max_y {
                continue;
            }
            let inv_z = p.map(|q| 1.0 / q.z);
            for y in (min_y as usize)..=(max_y as usize) {
                for x in (min_x as usize)..=(max_x as usize) {
                    let pix = (x as f64, y as f64);
                    let b = [
                        edge(s[1], s[2], pix) / area,
                        edge(s[2], s[0], pix) / area,
                        edge(s[0], s[1], pix) / area,
                    ];
                    if b.iter().any(|v| *v < 0.0) {
                        continue;
                    }
                    let iz = b[0] * inv_z[0] + b[1] * inv_z[1] + b[2] * inv_z[2];
                    let point = (p[0] * (b[0] * inv_z[0])
                        + p[1] * (b[1] * inv_z[1])
                        + p[2] * (b[2] * inv_z[2]))
                        / iz;
                    let slot = &mut hits[y * w + x];
                    if slot.is_none_or(|old| point.z < old.depth) {
                        *slot = Some(Hit {
                            world: rt * (point - t),
                            normal,
                            depth: point.z,
                            object: tri.object,
                        });
                    }
                }
            }
        }
    }
    Buffers {
        width: w,
        height: h,
        hits,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use posediff_geometry::{ImageSize, Intrinsics, Pose};

    fn camera() -> Camera {
        Camera::new(
            Intrinsics::new(100.0, 100.0, 31.5, 23.5).unwrap(),
            Pose::identity(),
            ImageSize::new(64, 48).unwrap(),
        )
    }

    fn quad(z0: f64, z1: f64, object: u32) -> Vec<Triangle> {
        // A tilted plane spanning x, y ∈ [−1, 1], depth from z0 (left) to z1 (right).
        let v = |x: f64, y: f64| Vector3::new(x, y, z0 + (z1 - z0) * (x + 1.0) / 2.0);
        vec![
            Triangle {
                v: [v(-1.0, -1.0), v(1.0, -1.0), v(1.0, 1.0)],
                object,
            },
            Triangle {
                v: [v(-1.0, -1.0), v(1.0, 1.0), v(-1.0, 1.0)],
                object,
            },
        ]
    }

    #[test]
    fn every_hit_lies_on_its_pixel_ray() {
        let cam = camera();
        let buf = rasterise(&quad(3.0, 6.0, 0), &cam, 0.1);
        let mut count = 0;
        for y in 0..buf.height {
            for x in 0..buf.width {
                if let Some(hit) = buf.at(x, y) {
                    let p = cam.project(&hit.world.into()).unwrap();
                    assert!((p.x - x as f64).abs() < 1e-9 && (p.y - y as f64).abs() < 1e-9);
                    count += 1;
                }
            }
        }
        assert!(count > 500, "{count}");
    }

    #[test]
    fn the_nearer_surface_wins_and_clipping_keeps_the_rest() {
        let cam = camera();
        let mut tris = quad(5.0, 5.0, 1);
        tris.extend(quad(3.0, 3.0, 2));
        let buf = rasterise(&tris, &cam, 0.1);
        let centre = buf.at(32, 24).unwrap();
        assert_eq!(centre.object, 2);
        assert!((centre.depth - 3.0).abs() < 1e-12);
        // A plane crossing the camera plane: only its front part is drawn.
        let crossing = quad(-2.0, 4.0, 3);
        let buf = rasterise(&crossing, &cam, 0.5);
        assert!(buf.hits.iter().flatten().all(|h| h.depth >= 0.5 - 1e-12));
        assert!(buf.hits.iter().flatten().count() > 50);
    }
}
