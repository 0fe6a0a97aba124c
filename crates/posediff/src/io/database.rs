//! COLMAP 4.2's `database.db` (the SQLite store of COLMAP, GLOMAP and hloc), written from a
//! run: its schema exactly as pycolmap 4.2.1 creates it (rigs, rig sensors, cameras, frames,
//! frame data, images, pose priors, keypoints, descriptors, matches, two-view geometries),
//! through rusqlite with its bundled SQLite.
//!
//! What a run knows goes in: a camera per distinct estimated camera (its lens model and
//! parameters, `prior_focal_length = 1`: the focal is an estimate), a camera per image that was
//! not estimated (SIMPLE_RADIAL with COLMAP's `1.2·max(W, H)` prior, `prior_focal_length = 0`);
//! a rig per camera and a frame per image, as COLMAP 4's extraction writes them; the keypoints
//! that occur in verified matches (in COLMAP pixels: the photo's pixel, `+0.5`), each pair's
//! verified matches both as `matches` and as the inliers of an `UNCALIBRATED` two-view geometry
//! with its fundamental matrix (the eight-point fit of those inliers). Descriptors are not kept
//! by a run, so the `descriptors` table is empty: COLMAP's and GLOMAP's mappers read none, its
//! matchers need them.

use std::collections::HashSet;
use std::path::Path;

use posediff_geometry::PairMatches;
use rusqlite::{Connection, params};

use crate::error::{PosediffError, Result};
use crate::io::colmap::{ColmapModel, PIXEL_CENTRE_OFFSET};
use crate::reconstruction::Reconstruction;

/// COLMAP's schema (4.2), as pycolmap 4.2.1's `Database.open` creates it.
const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS rigs (rig_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, ref_sensor_id INTEGER NOT NULL, ref_sensor_type INTEGER NOT NULL);
CREATE UNIQUE INDEX IF NOT EXISTS rig_ref_sensor_assignment ON rigs(ref_sensor_id, ref_sensor_type);
CREATE TABLE IF NOT EXISTS rig_sensors (rig_id INTEGER NOT NULL, sensor_id INTEGER NOT NULL, sensor_type INTEGER NOT NULL, sensor_from_rig BLOB, FOREIGN KEY(rig_id) REFERENCES rigs(rig_id) ON DELETE CASCADE);
CREATE UNIQUE INDEX IF NOT EXISTS rig_sensor_assignment ON rig_sensors(sensor_id, sensor_type);
CREATE TABLE IF NOT EXISTS cameras (camera_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, model INTEGER NOT NULL, width INTEGER NOT NULL, height INTEGER NOT NULL, params BLOB, prior_focal_length INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS frames (frame_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, rig_id INTEGER NOT NULL, FOREIGN KEY(rig_id) REFERENCES rigs(rig_id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS frame_data (frame_id INTEGER NOT NULL, data_id INTEGER NOT NULL, sensor_id INTEGER NOT NULL, sensor_type INTEGER NOT NULL, FOREIGN KEY(frame_id) REFERENCES frames(frame_id) ON DELETE CASCADE);
CREATE UNIQUE INDEX IF NOT EXISTS frame_sensor_assignment ON frame_data(data_id, sensor_type);
CREATE TABLE IF NOT EXISTS images (image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, name TEXT NOT NULL UNIQUE, camera_id INTEGER NOT NULL, CONSTRAINT image_id_check CHECK(image_id >= 0 and image_id < 2147483647), FOREIGN KEY(camera_id) REFERENCES cameras(camera_id));
CREATE UNIQUE INDEX IF NOT EXISTS index_name ON images(name);
CREATE TABLE IF NOT EXISTS pose_priors (pose_prior_id INTEGER PRIMARY KEY NOT NULL, corr_data_id INTEGER NOT NULL, corr_sensor_id INTEGER NOT NULL, corr_sensor_type INTEGER NOT NULL, position BLOB, position_covariance BLOB, gravity BLOB, coordinate_system INTEGER NOT NULL);
CREATE UNIQUE INDEX IF NOT EXISTS pose_prior_data_assignment ON pose_priors(corr_data_id, corr_sensor_id, corr_sensor_type);
CREATE TABLE IF NOT EXISTS keypoints (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB, FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS descriptors (image_id INTEGER PRIMARY KEY NOT NULL, type INTEGER NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB, FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE IF NOT EXISTS matches (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB);
CREATE TABLE IF NOT EXISTS two_view_geometries (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB, config INTEGER NOT NULL, F BLOB, E BLOB, H BLOB, qvec BLOB, tvec BLOB, camera1 BLOB, camera2 BLOB);
";

/// COLMAP's `kMaxNumImages`: pair ids are `id1 · 2147483647 + id2`, `id1 < id2`.
const MAX_IMAGES: i64 = 2_147_483_647;
/// `SensorType::CAMERA`.
const SENSOR_CAMERA: i64 = 0;
/// `TwoViewGeometry::UNCALIBRATED`.
const UNCALIBRATED: i64 = 3;

/// COLMAP's pair id of images `a` and `b` (ids from 1).
pub fn pair_id(a: u32, b: u32) -> i64 {
    let (a, b) = if a < b { (a, b) } else { (b, a) };
    i64::from(a) * MAX_IMAGES + i64::from(b)
}

fn sql(path: &Path) -> impl Fn(rusqlite::Error) -> PosediffError + '_ {
    move |e| PosediffError::invalid(path, format!("SQLite: {e}"))
}

fn f64_blob(values: &[f64]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// What was written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DatabaseSummary {
    /// Cameras.
    pub cameras: usize,
    /// Images.
    pub images: usize,
    /// Pairs with verified matches.
    pub pairs: usize,
}

/// Writes `r` and its verified `pairs` as a new COLMAP database at `path` (which must not
/// exist).
///
/// # Errors
/// `path` exists; SQLite or OpenCV errors; pairs naming images out of range.
pub fn write_database(
    path: &Path,
    r: &Reconstruction,
    pairs: &[PairMatches],
) -> Result<DatabaseSummary> {
    if path.exists() {
        return Err(PosediffError::invalid(
            path,
            "exists: a database is written new (remove it, or choose another path)",
        ));
    }
    let e = sql(path);
    let mut db = Connection::open(path).map_err(&e)?;
    db.execute_batch(SCHEMA).map_err(&e)?;
    let tx = db.transaction().map_err(&e)?;
    let model = ColmapModel::from_reconstruction(r)?;
    let model_ids = crate::io::colmap::model_id_of;
    // Cameras: the model's, then one per image without a camera.
    let mut camera_of: Vec<u32> = vec![0; r.images.len()];
    let mut cameras = 0;
    for c in &model.cameras {
        tx.execute(
            "INSERT INTO cameras (camera_id, model, width, height, params, prior_focal_length) VALUES (?1, ?2, ?3, ?4, ?5, 1)",
            params![i64::from(c.id), model_ids(&c.model)?, c.width as i64, c.height as i64, f64_blob(&c.params)],
        ).map_err(&e)?;
        cameras += 1;
    }
    for image in &model.images {
        camera_of[image.id as usize - 1] = image.camera_id;
    }
    let mut next_camera = model.cameras.len() as u32 + 1;
    for (i, record) in r.images.iter().enumerate() {
        if camera_of[i] != 0 {
            continue;
        }
        let s = record.camera.size;
        let (w, h) = (f64::from(s.width()), f64::from(s.height()));
        let params = [1.2 * w.max(h), w / 2.0, h / 2.0, 0.0];
        tx.execute(
            "INSERT INTO cameras (camera_id, model, width, height, params, prior_focal_length) VALUES (?1, 2, ?2, ?3, ?4, 0)",
            params![i64::from(next_camera), i64::from(s.width()), i64::from(s.height()), f64_blob(&params)],
        ).map_err(&e)?;
        camera_of[i] = next_camera;
        next_camera += 1;
        cameras += 1;
    }
    let mut rigs: HashSet<u32> = HashSet::new();
    for (i, record) in r.images.iter().enumerate() {
        let (image_id, camera_id) = (i as i64 + 1, i64::from(camera_of[i]));
        if rigs.insert(camera_of[i]) {
            tx.execute(
                "INSERT INTO rigs (rig_id, ref_sensor_id, ref_sensor_type) VALUES (?1, ?1, ?2)",
                params![camera_id, SENSOR_CAMERA],
            )
            .map_err(&e)?;
        }
        tx.execute(
            "INSERT INTO images (image_id, name, camera_id) VALUES (?1, ?2, ?3)",
            params![image_id, record.camera.image, camera_id],
        )
        .map_err(&e)?;
        tx.execute(
            "INSERT INTO frames (frame_id, rig_id) VALUES (?1, ?2)",
            params![image_id, camera_id],
        )
        .map_err(&e)?;
        tx.execute(
            "INSERT INTO frame_data (frame_id, data_id, sensor_id, sensor_type) VALUES (?1, ?1, ?2, ?3)",
            params![image_id, camera_id, SENSOR_CAMERA],
        )
        .map_err(&e)?;
        // The keypoints of the record (those in matches, keypoint-id order), COLMAP pixels.
        let data: Vec<u8> = record
            .keypoints
            .iter()
            .flat_map(|k| {
                let xy = record.camera.photo_pixel(k.xy);
                [
                    (xy[0] + PIXEL_CENTRE_OFFSET) as f32,
                    (xy[1] + PIXEL_CENTRE_OFFSET) as f32,
                ]
            })
            .flat_map(f32::to_le_bytes)
            .collect();
        tx.execute(
            "INSERT INTO keypoints (image_id, rows, cols, data) VALUES (?1, ?2, 2, ?3)",
            params![image_id, record.keypoints.len() as i64, data],
        )
        .map_err(&e)?;
    }
    // Each image's keypoint ids in matches, sorted: a keypoint's row is its id's rank (as
    // `Reconstruction::triangulate` numbers the record's keypoints).
    let mut ids: Vec<Vec<u32>> = vec![Vec::new(); r.images.len()];
    for p in pairs {
        if p.first >= ids.len() || p.second >= ids.len() {
            return Err(PosediffError::InvalidArgument(format!(
                "pair ({}, {}) for {} images",
                p.first,
                p.second,
                ids.len()
            )));
        }
        ids[p.first].extend(&p.idx1);
        ids[p.second].extend(&p.idx2);
    }
    for list in &mut ids {
        list.sort_unstable();
        list.dedup();
    }
    let row = |image: usize, id: u32| -> Result<u32> {
        ids[image]
            .binary_search(&id)
            .map(|k| k as u32)
            .map_err(|_| PosediffError::InvalidArgument(format!("keypoint {id} of image {image}")))
    };
    let mut written = 0;
    for p in pairs.iter().filter(|p| !p.is_empty()) {
        // COLMAP orders a pair by image id; its first column is the smaller id's keypoint.
        let swap = p.first > p.second;
        let mut data = Vec::with_capacity(p.len() * 8);
        let mut x1 = Vec::with_capacity(p.len());
        let mut x2 = Vec::with_capacity(p.len());
        for k in 0..p.len() {
            let (a, b) = (row(p.first, p.idx1[k])?, row(p.second, p.idx2[k])?);
            let (first, second) = (&r.images[p.first], &r.images[p.second]);
            let pa = first.camera.photo_pixel(first.keypoints[a as usize].xy);
            let pb = second.camera.photo_pixel(second.keypoints[b as usize].xy);
            let ((a, pa), (b, pb)) = if swap {
                ((b, pb), (a, pa))
            } else {
                ((a, pa), (b, pb))
            };
            data.extend(a.to_le_bytes());
            data.extend(b.to_le_bytes());
            x1.push([pa[0] + PIXEL_CENTRE_OFFSET, pa[1] + PIXEL_CENTRE_OFFSET]);
            x2.push([pb[0] + PIXEL_CENTRE_OFFSET, pb[1] + PIXEL_CENTRE_OFFSET]);
        }
        let id = pair_id(p.first as u32 + 1, p.second as u32 + 1);
        tx.execute(
            "INSERT INTO matches (pair_id, rows, cols, data) VALUES (?1, ?2, 2, ?3)",
            params![id, p.len() as i64, data],
        )
        .map_err(&e)?;
        // The eight-point fit of the inliers, `x2ᵀ F x1 = 0`, row-major (pycolmap reads it so:
        // scripts/check_database.py checks the epipolar distances of the inliers).
        let f = posediff_matching::two_view::fundamental_least_squares(&x1, &x2)?.map(|f| {
            f64_blob(&[
                f[(0, 0)],
                f[(0, 1)],
                f[(0, 2)],
                f[(1, 0)],
                f[(1, 1)],
                f[(1, 2)],
                f[(2, 0)],
                f[(2, 1)],
                f[(2, 2)],
            ])
        });
        tx.execute(
            "INSERT INTO two_view_geometries (pair_id, rows, cols, data, config, F) VALUES (?1, ?2, 2, ?3, ?4, ?5)",
            params![id, p.len() as i64, data, UNCALIBRATED, f],
        )
        .map_err(&e)?;
        written += 1;
    }
    tx.commit().map_err(&e)?;
    Ok(DatabaseSummary {
        cameras,
        images: r.images.len(),
        pairs: written,
    })
}
