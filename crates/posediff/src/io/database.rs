//! COLMAP 4.2's `database.db` (the SQLite store of COLMAP, GLOMAP and hloc): its schema
//! exactly as pycolmap 4.2.1 creates it (rigs, rig sensors, cameras, frames, frame data,
//! images, pose priors, keypoints, descriptors, matches, two-view geometries), through
//! rusqlite with its bundled SQLite. Two writers:
//!
//! - [`Database`], `--database D`: the run's store ([`posediff_pipeline::store`]). Features
//!   and verified matches are read from it first and written to it as they are made, in
//!   chunked commits, so that an interrupted run resumes. It holds a camera per image with its
//!   prior (COLMAP's default), every keypoint and descriptor, each matched pair's matches
//!   before verification as `matches` (SIFT's and ORB's mutual nearest neighbours, LightGlue's
//!   matches, as COLMAP's matchers and hloc store them) and its verified ones as the inliers
//!   of an `UNCALIBRATED` two-view geometry (a `DEGENERATE` one with no rows where too few
//!   verified, so that the pair is not matched again).
//!   A table of its own, `posediff_store`, records which matcher and settings made the
//!   features, so that a run with others is refused instead of mixing them, and each stored
//!   image's content (`image:<name>` → `sha256:<hex>`), so that a file replaced under the
//!   same name is refused instead of being given another photo's features.
//! - [`write_database`], Python's `write(..., formats=["database"])`: a snapshot of a result.
//!   What a run knows goes in: a camera per distinct estimated camera (its lens model and
//!   parameters, `prior_focal_length = 1`: the focal is an estimate), a camera per image that was
//!   not estimated (SIMPLE_RADIAL with COLMAP's `1.2·max(W, H)` prior, `prior_focal_length = 0`);
//!   a rig per camera and a frame per image, as COLMAP 4's extraction writes them; the keypoints
//!   that occur in verified matches (in COLMAP pixels: the photo's pixel, `+0.5`), each pair's
//!   verified matches both as `matches` and as the inliers of an `UNCALIBRATED` two-view geometry
//!   with its fundamental matrix (the eight-point fit of those inliers). Descriptors are not kept
//!   by the snapshot, so its `descriptors` table is empty: COLMAP's and GLOMAP's mappers read
//!   none, its matchers need them.
//!
//! [`Database::open_for_mapping`] reads any writer's database for `posediff map`.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use posediff_geometry::{ImageSize, PairMatches};
use posediff_matching::features::{byte_floats, whole_bytes};
use posediff_matching::{Descriptors, ImageFeatures};
use posediff_pipeline::store::{FeatureStore, StoredMatches};
use rusqlite::{Connection, OptionalExtension, params};

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
/// `TwoViewGeometry::DEGENERATE`: a pair that verified too few matches.
const DEGENERATE: i64 = 1;
/// `TwoViewGeometry::UNDEFINED`: not verified.
const UNDEFINED: i64 = 0;
/// `TwoViewGeometry::WATERMARK`: matches on a watermark or border, not the scene.
const WATERMARK: i64 = 7;
/// `TwoViewGeometry::MULTIPLE`: several geometries; COLMAP's mappers skip it as a pair.
const MULTIPLE: i64 = 8;
/// `FeatureExtractorType::SIFT` (8-bit descriptors).
const DESCRIPTOR_SIFT: i64 = 0;
/// `FeatureExtractorType::ALIKED_N16ROT` (float descriptors, their bytes as 8-bit columns).
const DESCRIPTOR_ALIKED_N16ROT: i64 = 1;
/// `FeatureExtractorType::UNDEFINED`: ORB's bits, ALIKED n16's and DISK's floats.
const DESCRIPTOR_UNDEFINED: i64 = -1;
/// `CameraModelId::SIMPLE_RADIAL`.
const SIMPLE_RADIAL: i64 = 2;

/// posediff's own table: which matcher and settings made the stored features and matches.
const STORE_TABLE: &str = "CREATE TABLE IF NOT EXISTS posediff_store (key TEXT PRIMARY KEY NOT NULL, value TEXT NOT NULL);";

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
        let (first, second) = (&r.images[p.first], &r.images[p.second]);
        let rows = (0..p.len())
            .map(|k| {
                let (a, b) = (row(p.first, p.idx1[k])?, row(p.second, p.idx2[k])?);
                let pa = first.camera.photo_pixel(first.keypoints[a as usize].xy);
                let pb = second.camera.photo_pixel(second.keypoints[b as usize].xy);
                Ok(((a, Some(pa)), (b, Some(pb))))
            })
            .collect::<Result<Vec<_>>>()?;
        // COLMAP orders a pair by image id (here the image's index + 1).
        let (data, x1, x2) = colmap_rows(rows.into_iter(), p.first > p.second);
        let id = pair_id(p.first as u32 + 1, p.second as u32 + 1);
        insert_pair(&tx, &e, id, (p.len(), &data), None, (&x1, &x2))?;
        written += 1;
    }
    tx.commit().map_err(&e)?;
    Ok(DatabaseSummary {
        cameras,
        images: r.images.len(),
        pairs: written,
    })
}

/// A pair's matches as COLMAP stores them (keypoint ids, the smaller image id's first: the
/// pair's own order unless `swap`, as little-endian `u32` pairs) and, where both keypoints'
/// pixels are known, their COLMAP pixels (`+0.5`) in the same order. `matches` gives each
/// match's keypoint id and photo pixel in the pair's first image, then in its second.
fn colmap_rows(
    matches: impl ExactSizeIterator<Item = ((u32, Option<[f64; 2]>), (u32, Option<[f64; 2]>))>,
    swap: bool,
) -> (Vec<u8>, Vec<[f64; 2]>, Vec<[f64; 2]>) {
    let mut data = Vec::with_capacity(matches.len() * 8);
    let mut x1 = Vec::with_capacity(matches.len());
    let mut x2 = Vec::with_capacity(matches.len());
    for (first, second) in matches {
        // COLMAP orders a pair by image id: the smaller id's keypoint first.
        let ((u, pa), (v, pb)) = if swap {
            (second, first)
        } else {
            (first, second)
        };
        data.extend(u.to_le_bytes());
        data.extend(v.to_le_bytes());
        if let (Some(pa), Some(pb)) = (pa, pb) {
            x1.push([pa[0] + PIXEL_CENTRE_OFFSET, pa[1] + PIXEL_CENTRE_OFFSET]);
            x2.push([pb[0] + PIXEL_CENTRE_OFFSET, pb[1] + PIXEL_CENTRE_OFFSET]);
        }
    }
    (data, x1, x2)
}

/// The stored keypoints of a pair's first and second image, where known.
type PairKeypoints<'a> = (Option<&'a Vec<[f64; 2]>>, Option<&'a Vec<[f64; 2]>>);

/// [`colmap_rows`] of `p`, its keypoints' pixels from `keypoints` (of its first and second
/// image, by keypoint id).
fn stored_rows(
    p: &PairMatches,
    swap: bool,
    (ka, kb): PairKeypoints<'_>,
) -> (Vec<u8>, Vec<[f64; 2]>, Vec<[f64; 2]>) {
    let pixel =
        |kp: Option<&Vec<[f64; 2]>>, id: u32| kp.and_then(|kp| kp.get(id as usize)).copied();
    colmap_rows(
        p.idx1
            .iter()
            .zip(&p.idx2)
            .map(|(&u, &v)| ((u, pixel(ka, u)), (v, pixel(kb, v)))),
        swap,
    )
}

/// Writes a pair's `rows` verified matches (`data`, COLMAP's order) as the inliers of its
/// two-view geometry: `UNCALIBRATED` with F, the eight-point fit of the inliers `x1`, `x2` in
/// COLMAP pixels (`x2ᵀ F x1 = 0`, row-major, as pycolmap reads it: scripts/check_database.py
/// checks the epipolar distances), or `DEGENERATE` without rows where too few verified; and as
/// `matches` the raw ones before verification when given (`raw_rows`, the same layout), else
/// the verified ones.
fn insert_pair(
    tx: &rusqlite::Transaction<'_>,
    e: &impl Fn(rusqlite::Error) -> PosediffError,
    id: i64,
    (rows, data): (usize, &[u8]),
    raw_rows: Option<(usize, &[u8])>,
    (x1, x2): (&[[f64; 2]], &[[f64; 2]]),
) -> Result<()> {
    let (raw_count, raw_data) = raw_rows.unwrap_or((rows, data));
    tx.execute(
        "INSERT OR REPLACE INTO matches (pair_id, rows, cols, data) VALUES (?1, ?2, 2, ?3)",
        params![id, raw_count as i64, raw_data],
    )
    .map_err(e)?;
    let f = if rows > 0 && x1.len() == rows {
        posediff_matching::two_view::fundamental_least_squares(x1, x2)?.map(|f| {
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
        })
    } else {
        None
    };
    let config = if rows == 0 { DEGENERATE } else { UNCALIBRATED };
    tx.execute(
        "INSERT OR REPLACE INTO two_view_geometries (pair_id, rows, cols, data, config, F) VALUES (?1, ?2, 2, ?3, ?4, ?5)",
        params![id, rows as i64, data, config, f],
    )
    .map_err(e)?;
    Ok(())
}

/// What made a store's features and matches: a run with other settings is refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StoreIdentity {
    /// The matcher (`sift`, `aliked-lightglue`, …).
    pub matcher: String,
    /// The matching settings and masks, as JSON.
    pub settings: String,
}

impl StoreIdentity {
    /// Its `posediff_store` rows.
    fn entries(&self) -> [(&'static str, &str); 2] {
        [
            ("matcher", self.matcher.as_str()),
            ("settings", self.settings.as_str()),
        ]
    }
}

/// The `posediff_store` key of an image's content digest.
fn content_key(name: &str) -> String {
    format!("image:{name}")
}

/// `sha256:<hex>` of a file's bytes (streamed).
fn content_digest(path: &Path) -> Result<String> {
    use sha2::Digest;
    use std::io::Read;
    let mut file = std::fs::File::open(path).map_err(|e| PosediffError::invalid(path, e))?;
    let mut hasher = sha2::Sha256::new();
    let mut buffer = vec![0u8; 1 << 16];
    loop {
        let n = file
            .read(&mut buffer)
            .map_err(|e| PosediffError::invalid(path, e))?;
        if n == 0 {
            break;
        }
        hasher.update(&buffer[..n]);
    }
    let digest = hasher.finalize();
    let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
    Ok(format!("sha256:{hex}"))
}

/// The `posediff_store` value under `key`, if any.
fn store_value(conn: &Connection, key: &str) -> rusqlite::Result<Option<String>> {
    conn.query_row(
        "SELECT value FROM posediff_store WHERE key = ?1",
        params![key],
        |r| r.get(0),
    )
    .optional()
}

/// One image of a run, as the store names it.
#[derive(Debug, Clone, PartialEq)]
pub struct StoreImage {
    /// The file.
    pub path: PathBuf,
    /// Its name (relative to the input folder): the database's key.
    pub name: String,
    /// Its EXIF focal tags (the camera's prior focal, as COLMAP reads it).
    pub focal: posediff_pipeline::options::ExifFocal,
    /// Images of the same key and size share one COLMAP camera (and its rig), as COLMAP's
    /// `ImageReader.single_camera` / `single_camera_per_folder` do; `None`: a camera of its
    /// own (COLMAP's default). [`shared_camera_key`] gives it from `cameras.mode`.
    pub camera: Option<String>,
}

/// Which images share a camera in the database, from `cameras.mode` and the image's hint:
/// `single` all (of one size), `per-folder` a folder's, `auto` an EXIF camera's (make, model,
/// focal; images without EXIF, and every image of a set without EXIF, whose cameras the mapper
/// decides from the data, get their own), `per-image` none.
#[must_use]
pub fn shared_camera_key(
    mode: posediff_pipeline::options::CameraMode,
    hint: Option<&posediff_pipeline::options::CameraHint>,
) -> Option<String> {
    use posediff_pipeline::options::CameraMode;
    match mode {
        CameraMode::Single => Some("single".into()),
        CameraMode::PerImage => None,
        CameraMode::PerFolder => Some(format!("folder {}", hint.map_or("", |h| &h.folder))),
        CameraMode::Auto => hint
            .and_then(|h| h.device.as_deref())
            .map(|d| format!("exif {d}")),
    }
}

/// The `posediff_store` key of the camera that images of `key` and size `w`×`h` share.
fn camera_store_key(key: &str, w: u32, h: u32) -> String {
    format!("camera {w}x{h} {key}")
}

/// `--database`: COLMAP's database as the run's [`FeatureStore`], held exclusively while the
/// run lasts (SQLite's exclusive locking mode: a second writer, posediff's or COLMAP's, is
/// refused with an error instead of waiting or interleaving).
pub struct Database {
    path: PathBuf,
    conn: Mutex<Connection>,
    /// The run's images by path.
    by_path: HashMap<PathBuf, StoreImage>,
    /// The images of the last [`FeatureStore::features`] list.
    run: Mutex<RunImages>,
    /// The stored keypoints of the run's images by id, COLMAP pixels (for the pairs' F).
    keypoints: Mutex<HashMap<i64, Vec<[f64; 2]>>>,
    /// Descriptors kind of the matcher.
    matcher: String,
    /// `posediff map`: read what the database holds (any writer's), compute and write nothing.
    map_only: bool,
    /// `--from`: a worker's database, read (features with their descriptors, pairs) and never
    /// written, so that any number of processes read it at once.
    source: bool,
}

impl std::fmt::Debug for Database {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Database")
            .field("path", &self.path)
            .finish()
    }
}

/// A pair selection as `posediff_store` keeps it (`selection:<rules>`): the image names it was
/// made for, in the run's order, and the pairs as indices into them.
#[derive(serde::Serialize, serde::Deserialize)]
struct StoredSelection {
    images: Vec<String>,
    pairs: Vec<(usize, usize)>,
}

/// The run's images: their database ids (`-1`: no features yet) and their index by path.
#[derive(Debug, Default)]
struct RunImages {
    ids: Vec<i64>,
    index: HashMap<PathBuf, usize>,
}

/// The counts of a database, for logs and tests.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DatabaseCounts {
    /// Images.
    pub images: usize,
    /// Images with keypoints.
    pub keypoints: usize,
    /// Pairs with a two-view geometry (verified or not).
    pub pairs: usize,
    /// Of those, pairs with verified matches.
    pub verified: usize,
}

/// A read-only connection to the existing database at `path` that fails at once on a writer's
/// lock.
fn open_read_only(path: &Path) -> Result<Connection> {
    if !path.is_file() {
        return Err(PosediffError::NotFound(path.to_owned()));
    }
    let wrap = sqlite_error(path);
    let conn = Connection::open_with_flags(path, rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY)
        .map_err(wrap)?;
    conn.busy_timeout(std::time::Duration::ZERO).map_err(wrap)?;
    Ok(conn)
}

/// SQLite's errors on the database at `path` as posediff's: a lock or a file that is not
/// SQLite named with the fix, anything else with SQLite's message.
fn sqlite_error(path: &Path) -> impl Fn(rusqlite::Error) -> PosediffError + Copy + '_ {
    move |e| {
        lock_error(path, &e).unwrap_or_else(|| PosediffError::invalid(path, format!("SQLite: {e}")))
    }
}

fn lock_error(path: &Path, e: &rusqlite::Error) -> Option<PosediffError> {
    match e {
        rusqlite::Error::SqliteFailure(f, _)
            if matches!(
                f.code,
                rusqlite::ErrorCode::DatabaseBusy | rusqlite::ErrorCode::DatabaseLocked
            ) =>
        {
            Some(PosediffError::invalid(
                path,
                "is in use by another process (a posediff or COLMAP run writing it): wait for it \
                 to finish, or give another --database",
            ))
        }
        rusqlite::Error::SqliteFailure(f, _) if f.code == rusqlite::ErrorCode::NotADatabase => {
            Some(PosediffError::invalid(
                path,
                "is not a SQLite database: give the path of a COLMAP database.db or of a new file",
            ))
        }
        _ => None,
    }
}

impl Database {
    /// Opens (or creates) the database at `path` for a run of `images` whose features come
    /// from `identity`, and takes it exclusively.
    ///
    /// # Errors
    /// A folder that does not exist; a file that is not SQLite; a database in use by another
    /// process; one written by another tool (no `posediff_store` table but images), or by a
    /// run with another matcher or other settings (each named, with the fix).
    pub fn open(path: &Path, identity: &StoreIdentity, images: Vec<StoreImage>) -> Result<Self> {
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty())
            && !parent.is_dir()
        {
            return Err(PosediffError::invalid(
                path,
                "its folder does not exist (create it first)",
            ));
        }
        if path.is_dir() {
            return Err(PosediffError::invalid(
                path,
                "is a folder: --database names a file (e.g. out/../database.db)",
            ));
        }
        let wrap = sqlite_error(path);
        let conn = Connection::open(path).map_err(wrap)?;
        conn.busy_timeout(std::time::Duration::ZERO).map_err(wrap)?;
        // Exclusive from the first statement to the end of the run.
        conn.pragma_update(None, "locking_mode", "EXCLUSIVE")
            .map_err(wrap)?;
        conn.execute_batch("BEGIN EXCLUSIVE;").map_err(wrap)?;
        let set_up = (|| -> Result<()> {
            let tables: i64 = conn
                .query_row(
                    "SELECT count(*) FROM sqlite_master WHERE type='table' AND name='posediff_store'",
                    [],
                    |r| r.get(0),
                )
                .map_err(wrap)?;
            let has_images: i64 = conn
                .query_row(
                    "SELECT count(*) FROM sqlite_master WHERE type='table' AND name='images'",
                    [],
                    |r| r.get(0),
                )
                .map_err(wrap)?;
            let foreign = tables == 0
                && has_images > 0
                && conn
                    .query_row("SELECT count(*) FROM images", [], |r| r.get::<_, i64>(0))
                    .map_err(wrap)?
                    > 0;
            if foreign {
                return Err(PosediffError::invalid(
                    path,
                    "holds images that another tool wrote (COLMAP, pycolmap, hloc): posediff \
                     cannot tell how its features were made. Map it with `posediff map --database \
                     D --images DIR --out OUT`, or give estimate a new --database",
                ));
            }
            conn.execute_batch(SCHEMA).map_err(wrap)?;
            conn.execute_batch(STORE_TABLE).map_err(wrap)?;
            for (key, value) in identity.entries() {
                let stored = store_value(&conn, key).map_err(wrap)?;
                match stored {
                    None => {
                        conn.execute(
                            "INSERT INTO posediff_store (key, value) VALUES (?1, ?2)",
                            params![key, value],
                        )
                        .map_err(wrap)?;
                    }
                    Some(s) if s == value => {}
                    Some(s) => {
                        return Err(PosediffError::invalid(
                            path,
                            format!(
                                "holds features made with {key} {s}, and this run asks for \
                                 {value}: run with the database's settings, or give another \
                                 --database"
                            ),
                        ));
                    }
                }
            }
            Ok(())
        })();
        match set_up {
            Ok(()) => conn.execute_batch("COMMIT;").map_err(wrap)?,
            Err(e) => {
                let _ = conn.execute_batch("ROLLBACK;");
                return Err(e);
            }
        }
        Ok(Self {
            path: path.to_owned(),
            conn: Mutex::new(conn),
            by_path: images.into_iter().map(|i| (i.path.clone(), i)).collect(),
            run: Mutex::new(RunImages::default()),
            keypoints: Mutex::new(HashMap::new()),
            matcher: identity.matcher.clone(),
            map_only: false,
            source: false,
        })
    }

    /// A read-only database: mapped (`map_only`) or a `--from` source.
    fn read_only(
        path: &Path,
        conn: Connection,
        images: Vec<StoreImage>,
        matcher: String,
        map_only: bool,
    ) -> Self {
        Self {
            path: path.to_owned(),
            conn: Mutex::new(conn),
            by_path: images.into_iter().map(|i| (i.path.clone(), i)).collect(),
            run: Mutex::new(RunImages::default()),
            keypoints: Mutex::new(HashMap::new()),
            matcher,
            map_only,
            source: !map_only,
        }
    }

    /// Opens the database at `path` to map what it holds (`posediff map`), whoever wrote it
    /// (posediff, COLMAP, pycolmap, hloc): keypoints and verified two-view geometries are read;
    /// nothing is computed or written.
    ///
    /// # Errors
    /// No such file; not SQLite; in use by a writer; no COLMAP tables.
    pub fn open_for_mapping(path: &Path, images: Vec<StoreImage>) -> Result<Self> {
        let conn = open_read_only(path)?;
        let wrap = sqlite_error(path);
        let tables: i64 = conn
            .query_row(
                "SELECT count(*) FROM sqlite_master WHERE type='table' AND name IN ('images', 'cameras', 'keypoints', 'two_view_geometries')",
                [],
                |r| r.get(0),
            )
            .map_err(wrap)?;
        if tables != 4 {
            return Err(PosediffError::invalid(
                path,
                "is not a COLMAP database (no images, cameras, keypoints and two_view_geometries tables)",
            ));
        }
        Ok(Self::read_only(path, conn, images, String::new(), true))
    }

    /// Opens the database at `path` as a source to import from (`--from`): read-only, so that
    /// the workers of a distributed run may all read one merged database at once; it must have
    /// been written by posediff with `identity`'s matcher and settings.
    ///
    /// # Errors
    /// No such file; not SQLite; in use by a writer; not written by posediff, or with another
    /// matcher or other settings (named, with the fix).
    pub fn open_source(
        path: &Path,
        identity: &StoreIdentity,
        images: Vec<StoreImage>,
    ) -> Result<Self> {
        let conn = open_read_only(path)?;
        let wrap = sqlite_error(path);
        let tables: i64 = conn
            .query_row(
                "SELECT count(*) FROM sqlite_master WHERE type='table' AND name='posediff_store'",
                [],
                |r| r.get(0),
            )
            .map_err(wrap)?;
        if tables == 0 {
            return Err(PosediffError::invalid(
                path,
                "was not written by posediff (no posediff_store table): --from imports \
                 posediff workers' databases (`posediff features|match --database W`)",
            ));
        }
        for (key, value) in identity.entries() {
            let stored = store_value(&conn, key).map_err(wrap)?;
            if stored.as_deref() != Some(value) {
                return Err(PosediffError::invalid(
                    path,
                    format!(
                        "holds features made with {key} {}, and this run asks for {value}: give \
                         --from databases filled with this run's matcher and settings",
                        stored.as_deref().unwrap_or("(none)")
                    ),
                ));
            }
        }
        Ok(Self::read_only(
            path,
            conn,
            images,
            identity.matcher.clone(),
            false,
        ))
    }

    /// The names of the images the database holds, by id.
    ///
    /// # Errors
    /// SQLite errors.
    pub fn image_names(&self) -> Result<Vec<String>> {
        let conn = self.conn();
        let e = self.wrap();
        let mut stmt = conn
            .prepare("SELECT name FROM images ORDER BY image_id")
            .map_err(&e)?;
        let names = stmt
            .query_map([], |r| r.get(0))
            .map_err(&e)?
            .collect::<std::result::Result<Vec<String>, _>>()
            .map_err(&e)?;
        Ok(names)
    }

    fn wrap(&self) -> impl Fn(rusqlite::Error) -> PosediffError + '_ {
        sqlite_error(&self.path)
    }

    fn conn(&self) -> std::sync::MutexGuard<'_, Connection> {
        self.conn
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Checks that `image`'s file is the photo whose features are stored under its name
    /// (databases written before the digests were kept, and images stored without one, are
    /// not checked).
    fn check_content(&self, conn: &Connection, image: &StoreImage) -> Result<()> {
        let Some(stored) =
            store_value(conn, &content_key(&image.name)).map_err(sqlite_error(&self.path))?
        else {
            return Ok(());
        };
        let now = content_digest(&image.path)?;
        if now != stored {
            return Err(PosediffError::invalid(
                &self.path,
                format!(
                    "holds the features of another photo named {:?} ({stored}; {} is {now}): \
                     the file was replaced since they were stored. Use a new database, or \
                     restore the photo",
                    image.name,
                    image.path.display()
                ),
            ));
        }
        Ok(())
    }

    fn image(&self, path: &Path) -> Result<&StoreImage> {
        self.by_path.get(path).ok_or_else(|| {
            PosediffError::InvalidArgument(format!(
                "{} is not an image of this run's database",
                path.display()
            ))
        })
    }

    fn writable(&self) -> Result<()> {
        if self.source {
            return Err(PosediffError::invalid(
                &self.path,
                "is open as a --from source: it is only read",
            ));
        }
        if self.map_only {
            return Err(PosediffError::invalid(
                &self.path,
                "is open to be mapped: it lacks features or matches this run needs (`posediff \
                 features` and `posediff match` add them)",
            ));
        }
        Ok(())
    }

    /// How many images, keypoint records and pairs the database holds.
    ///
    /// # Errors
    /// SQLite errors.
    pub fn counts(&self) -> Result<DatabaseCounts> {
        counts(&self.conn(), &self.path)
    }

    /// Takes into this database what `from` (a store of the same matcher and settings, e.g.
    /// a worker's copy filled with `--shard`) holds for the run's `images` and this one lacks:
    /// features first, then every matched pair (verified or not) between images both hold.
    /// Returns how many images and pairs came in.
    ///
    /// # Errors
    /// SQLite errors; features of the same image that differ between the two (the stores were
    /// not filled from the same images).
    pub fn import(&self, from: &Database, images: &[PathBuf]) -> Result<(usize, usize)> {
        let theirs = from.features(images)?;
        if theirs.iter().all(Option::is_none) {
            // Pairs only (a matching task's database): this one's features are not read.
            self.set_run(images)?;
            return Ok((0, self.import_pairs(from, images)?));
        }
        let mine = self.features(images)?;
        let (mut paths, mut new) = (Vec::new(), Vec::new());
        for (k, (m, t)) in mine.iter().zip(theirs).enumerate() {
            match (m, t) {
                (None, Some(t)) => {
                    paths.push(images[k].as_path());
                    new.push(t);
                }
                (Some(m), Some(t)) if m.keypoints != t.keypoints => {
                    return Err(PosediffError::invalid(
                        &from.path,
                        format!(
                            "holds other keypoints of {} than {}: it was not filled from the \
                             same images (or with the same settings)",
                            images[k].display(),
                            self.path.display()
                        ),
                    ));
                }
                _ => {}
            }
        }
        let imported = new.len();
        if !new.is_empty() {
            self.put_features(&paths, new)?;
        }
        self.set_run(images)?;
        self.import_selections(from)?;
        Ok((imported, self.import_pairs(from, images)?))
    }

    /// The pair selections `from` keeps that this database lacks (each is used only for the
    /// image list it was made for).
    fn import_selections(&self, from: &Database) -> Result<()> {
        let rows: Vec<(String, String)> = {
            let src = from.conn();
            let fe = from.wrap();
            let mut stmt = src
                .prepare("SELECT key, value FROM posediff_store WHERE key LIKE 'selection:%'")
                .map_err(&fe)?;
            stmt.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
                .map_err(&fe)?
                .collect::<std::result::Result<Vec<_>, _>>()
                .map_err(&fe)?
        };
        let conn = self.conn();
        let e = self.wrap();
        for (key, value) in rows {
            conn.execute(
                "INSERT OR IGNORE INTO posediff_store (key, value) VALUES (?1, ?2)",
                params![key, value],
            )
            .map_err(&e)?;
        }
        Ok(())
    }

    /// Makes `images` the run's list (their ids, `-1` where not stored) without reading any
    /// feature, as [`FeatureStore::features`] does.
    fn set_run(&self, images: &[PathBuf]) -> Result<()> {
        let conn = self.conn();
        let e = self.wrap();
        let mut stmt = conn
            .prepare_cached("SELECT image_id FROM images WHERE name = ?1")
            .map_err(&e)?;
        let mut ids = Vec::with_capacity(images.len());
        for path in images {
            let name = &self.image(path)?.name;
            ids.push(
                stmt.query_row(params![name], |r| r.get::<_, i64>(0))
                    .optional()
                    .map_err(&e)?
                    .unwrap_or(-1),
            );
        }
        let mut run = self
            .run
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        run.index = images.iter().cloned().zip(0..).collect();
        run.ids = ids;
        Ok(())
    }

    /// The pairs `from` holds and this database lacks, stored here (both have the run's list
    /// set by `features`). Where the two databases order a pair's images alike (a worker's
    /// copy of this one always does), its `matches` and `two_view_geometries` rows are copied
    /// as they are, F included; otherwise the matches are stored again through
    /// [`FeatureStore::put_matches`], which orders them by this database's ids and fits F.
    fn import_pairs(&self, from: &Database, images: &[PathBuf]) -> Result<usize> {
        let candidates = from.stored_pairs()?;
        let (mine, theirs) = (self.run_ids(), from.run_ids());
        let mut reordered = Vec::new();
        let mut copied = 0;
        {
            let mut conn = self.conn();
            let src = from.conn();
            let e = self.wrap();
            let fe = from.wrap();
            let tx = conn.transaction().map_err(&e)?;
            {
                let mut exists = tx
                    .prepare_cached("SELECT 1 FROM two_view_geometries WHERE pair_id = ?1")
                    .map_err(&e)?;
                let mut geometry = src
                    .prepare_cached(
                        "SELECT rows, cols, data, config, F, E, H, qvec, tvec, camera1, camera2 FROM two_view_geometries WHERE pair_id = ?1",
                    )
                    .map_err(&fe)?;
                let mut matches = src
                    .prepare_cached("SELECT rows, cols, data FROM matches WHERE pair_id = ?1")
                    .map_err(&fe)?;
                let mut put_geometry = tx
                    .prepare_cached(
                        "INSERT INTO two_view_geometries (pair_id, rows, cols, data, config, F, E, H, qvec, tvec, camera1, camera2) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12)",
                    )
                    .map_err(&e)?;
                let mut put_matches = tx
                    .prepare_cached(
                        "INSERT OR REPLACE INTO matches (pair_id, rows, cols, data) VALUES (?1, ?2, ?3, ?4)",
                    )
                    .map_err(&e)?;
                for &(i, j) in &candidates {
                    let (Some(&a), Some(&b), Some(&fa), Some(&fb)) =
                        (mine.get(i), mine.get(j), theirs.get(i), theirs.get(j))
                    else {
                        continue;
                    };
                    if a <= 0 || b <= 0 {
                        continue;
                    }
                    let id = pair_id(a.min(b) as u32, a.max(b) as u32);
                    if exists.exists(params![id]).map_err(&e)? {
                        continue;
                    }
                    if (a < b) != (fa < fb) {
                        reordered.push((i, j));
                        continue;
                    }
                    let old = pair_id(fa.min(fb) as u32, fa.max(fb) as u32);
                    let row: [rusqlite::types::Value; 11] = geometry
                        .query_row(params![old], |r| {
                            Ok(std::array::from_fn(|k| {
                                r.get::<_, rusqlite::types::Value>(k)
                                    .unwrap_or(rusqlite::types::Value::Null)
                            }))
                        })
                        .map_err(&fe)?;
                    let mut values = vec![rusqlite::types::Value::Integer(id)];
                    values.extend(row);
                    put_geometry
                        .execute(rusqlite::params_from_iter(values))
                        .map_err(&e)?;
                    let m: Option<[rusqlite::types::Value; 3]> = matches
                        .query_row(params![old], |r| {
                            Ok(std::array::from_fn(|k| {
                                r.get::<_, rusqlite::types::Value>(k)
                                    .unwrap_or(rusqlite::types::Value::Null)
                            }))
                        })
                        .optional()
                        .map_err(&fe)?;
                    if let Some(m) = m {
                        let mut values = vec![rusqlite::types::Value::Integer(id)];
                        values.extend(m);
                        put_matches
                            .execute(rusqlite::params_from_iter(values))
                            .map_err(&e)?;
                    }
                    copied += 1;
                }
            }
            tx.commit().map_err(&e)?;
        }
        if reordered.is_empty() {
            return Ok(copied);
        }
        let got = from.matches(&reordered)?;
        let raw = from.pair_rows("matches", &reordered)?;
        // The keypoints, for F (this also fills the keypoint cache `put_matches` reads).
        let features = self.features(images)?;
        let pair_of = |(i, j): (usize, usize), m: StoredMatches| {
            let point = |f: usize, k: u32| {
                features[f]
                    .as_ref()
                    .and_then(|fs| fs.keypoints.get(k as usize))
                    .copied()
                    .unwrap_or([0.0; 2])
            };
            PairMatches {
                first: i,
                second: j,
                kp1: m.iter().map(|&(k, _)| point(i, k)).collect(),
                kp2: m.iter().map(|&(_, l)| point(j, l)).collect(),
                idx1: m.iter().map(|&(k, _)| k).collect(),
                idx2: m.iter().map(|&(_, l)| l).collect(),
            }
        };
        let raw: Vec<Option<PairMatches>> = reordered
            .iter()
            .zip(raw)
            .map(|(&p, m)| m.map(|m| pair_of(p, m)))
            .collect();
        let pairs: Vec<PairMatches> = reordered
            .iter()
            .zip(got)
            .map(|(&p, m)| pair_of(p, m.unwrap_or_default()))
            .collect();
        self.put_matches_with_raw(&pairs, &raw)?;
        Ok(copied + pairs.len())
    }

    /// Each pair's rows of `table` (`two_view_geometries`: the verified matches; `matches`:
    /// those before verification), in the run's image order (`None`: no row).
    fn pair_rows(
        &self,
        table: &'static str,
        pairs: &[(usize, usize)],
    ) -> posediff_pipeline::Result<Vec<Option<StoredMatches>>> {
        let conn = self.conn();
        let e = self.wrap();
        let run = self
            .run
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let ids = &run.ids;
        let mut stmt = conn
            .prepare_cached(&format!(
                "SELECT rows, data FROM {table} WHERE pair_id = ?1"
            ))
            .map_err(&e)?;
        let mut out = Vec::with_capacity(pairs.len());
        for &(i, j) in pairs {
            let (a, b) = (run_id(ids, i)?, run_id(ids, j)?);
            let row: Option<(i64, Option<Vec<u8>>)> = stmt
                .query_row(params![pair_id(a as u32, b as u32)], |r| {
                    Ok((r.get(0)?, r.get(1)?))
                })
                .optional()
                .map_err(&e)?;
            out.push(match row {
                None => None,
                Some((rows, data)) => {
                    let m = decode_matches(&self.path, rows as usize, &data.unwrap_or_default())?;
                    // COLMAP's first column is the smaller id's keypoint.
                    Some(if a > b {
                        m.into_iter().map(|(x, y)| (y, x)).collect()
                    } else {
                        m
                    })
                }
            });
        }
        Ok(out)
    }

    /// The names of the last `features` list, in its order.
    fn run_names(&self) -> Vec<String> {
        let run = self
            .run
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let mut names = vec![String::new(); run.index.len()];
        for (path, &k) in &run.index {
            if let (Some(slot), Some(image)) = (names.get_mut(k), self.by_path.get(path)) {
                slot.clone_from(&image.name);
            }
        }
        names
    }

    /// The database ids of the last `features` list (`-1`: not in the database).
    fn run_ids(&self) -> Vec<i64> {
        self.run
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .ids
            .clone()
    }

    /// Every pair with a two-view geometry (verified or not) between two of the run's images
    /// that have features (indices into the last `features` list, smaller first).
    fn stored_pairs(&self) -> Result<Vec<(usize, usize)>> {
        self.pairs_where("1")
    }

    /// The pairs of the run's images whose two-view geometry meets the SQL `condition`
    /// (indices into the last `features` list, smaller first, sorted).
    fn pairs_where(&self, condition: &str) -> Result<Vec<(usize, usize)>> {
        let run = self
            .run
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let index: HashMap<i64, usize> = run
            .ids
            .iter()
            .copied()
            .zip(0..)
            .filter(|&(id, _)| id > 0)
            .collect();
        let conn = self.conn();
        let e = self.wrap();
        let mut stmt = conn
            .prepare(&format!(
                "SELECT pair_id FROM two_view_geometries WHERE {condition}"
            ))
            .map_err(&e)?;
        let ids = stmt
            .query_map([], |r| r.get::<_, i64>(0))
            .map_err(&e)?
            .collect::<std::result::Result<Vec<i64>, _>>()
            .map_err(&e)?;
        let mut pairs: Vec<(usize, usize)> = ids
            .into_iter()
            .filter_map(|id| {
                let (a, b) = (id / MAX_IMAGES, id % MAX_IMAGES);
                let (i, j) = (*index.get(&a)?, *index.get(&b)?);
                Some((i.min(j), i.max(j)))
            })
            .collect();
        pairs.sort_unstable();
        Ok(pairs)
    }

    /// The descriptors of `f` as COLMAP stores them: type, columns, bytes.
    fn encode_descriptors(&self, f: &ImageFeatures) -> Result<(i64, usize, Vec<u8>)> {
        match &f.descriptors {
            Descriptors::Bytes { data, dim } if self.matcher == "sift" => {
                Ok((DESCRIPTOR_SIFT, *dim, data.clone()))
            }
            Descriptors::Float { data, dim } if self.matcher == "sift" => {
                // OpenCV's SIFT values are whole numbers 0-255 in floats: COLMAP's 8 bits.
                let bytes = whole_bytes(data).ok_or_else(|| {
                    let v = data.iter().find(|&&v| whole_bytes(&[v]).is_none());
                    PosediffError::InvalidArgument(format!(
                        "a SIFT descriptor value {} is not 8-bit",
                        v.copied().unwrap_or(f32::NAN)
                    ))
                })?;
                Ok((DESCRIPTOR_SIFT, *dim, bytes))
            }
            Descriptors::Float { data, dim } => {
                let kind = if self.matcher == "aliked-n16rot-lightglue" {
                    DESCRIPTOR_ALIKED_N16ROT
                } else {
                    DESCRIPTOR_UNDEFINED
                };
                Ok((
                    kind,
                    dim * 4,
                    data.iter().flat_map(|v| v.to_le_bytes()).collect(),
                ))
            }
            // Byte rows under another matcher's name: stored as that matcher's floats (the same
            // distances when read back).
            Descriptors::Bytes { data, dim } => Ok((
                DESCRIPTOR_UNDEFINED,
                dim * 4,
                byte_floats(data)
                    .iter()
                    .flat_map(|v| v.to_le_bytes())
                    .collect(),
            )),
            Descriptors::Binary { data, words } => Ok((
                DESCRIPTOR_UNDEFINED,
                words * 8,
                data.iter().flat_map(|w| w.to_le_bytes()).collect(),
            )),
        }
    }

    /// The descriptors stored as `kind`, `cols`, `data` for this store's matcher.
    fn decode_descriptors(
        &self,
        kind: i64,
        rows: usize,
        cols: usize,
        data: &[u8],
    ) -> Result<Descriptors> {
        let bad = || {
            PosediffError::invalid(
                &self.path,
                format!(
                    "descriptors of type {kind}, {rows}×{cols}, {} bytes: not this store's",
                    data.len()
                ),
            )
        };
        if data.len() != rows * cols {
            return Err(bad());
        }
        match (self.matcher.as_str(), kind) {
            ("sift", DESCRIPTOR_SIFT) => Ok(Descriptors::Bytes {
                data: data.to_vec(),
                dim: cols,
            }),
            ("orb", DESCRIPTOR_UNDEFINED) if cols.is_multiple_of(8) => Ok(Descriptors::Binary {
                data: data
                    .chunks_exact(8)
                    .map(|c| u64::from_le_bytes(c.try_into().unwrap_or_default()))
                    .collect(),
                words: cols / 8,
            }),
            (m, DESCRIPTOR_UNDEFINED | DESCRIPTOR_ALIKED_N16ROT)
                if m != "sift" && m != "orb" && cols.is_multiple_of(4) =>
            {
                Ok(Descriptors::Float {
                    data: data
                        .chunks_exact(4)
                        .map(|c| f32::from_le_bytes(c.try_into().unwrap_or_default()))
                        .collect(),
                    dim: cols / 4,
                })
            }
            _ => Err(bad()),
        }
    }
}

fn counts(conn: &Connection, path: &Path) -> Result<DatabaseCounts> {
    let e = sql(path);
    let one = |q: &str| -> Result<usize> {
        conn.query_row(q, [], |r| r.get::<_, i64>(0))
            .map(|v| v as usize)
            .map_err(&e)
    };
    Ok(DatabaseCounts {
        images: one("SELECT count(*) FROM images")?,
        keypoints: one("SELECT count(*) FROM keypoints")?,
        pairs: one("SELECT count(*) FROM two_view_geometries")?,
        verified: one("SELECT count(*) FROM two_view_geometries WHERE rows > 0")?,
    })
}

/// Keypoints stored as COLMAP pixels (`cols` 2, 4 or 6 float32 per row: x, y first) in
/// OpenCV pixels.
fn decode_keypoints(path: &Path, rows: usize, cols: usize, data: &[u8]) -> Result<Vec<[f64; 2]>> {
    if cols < 2 || data.len() != rows * cols * 4 {
        return Err(PosediffError::invalid(
            path,
            format!("keypoints of {rows}×{cols} in {} bytes", data.len()),
        ));
    }
    Ok(data
        .chunks_exact(cols * 4)
        .map(|row| {
            let v = |k: usize| {
                f32::from_le_bytes([row[4 * k], row[4 * k + 1], row[4 * k + 2], row[4 * k + 3]])
            };
            [
                f64::from(v(0)) - PIXEL_CENTRE_OFFSET,
                f64::from(v(1)) - PIXEL_CENTRE_OFFSET,
            ]
        })
        .collect())
}

/// The match rows of a blob (`rows` × 2 u32).
fn decode_matches(path: &Path, rows: usize, data: &[u8]) -> Result<StoredMatches> {
    if data.len() != rows * 8 {
        return Err(PosediffError::invalid(
            path,
            format!("{rows} matches in {} bytes", data.len()),
        ));
    }
    Ok(data
        .chunks_exact(8)
        .map(|c| {
            (
                u32::from_le_bytes([c[0], c[1], c[2], c[3]]),
                u32::from_le_bytes([c[4], c[5], c[6], c[7]]),
            )
        })
        .collect())
}

impl FeatureStore for Database {
    fn features(
        &self,
        images: &[PathBuf],
    ) -> posediff_pipeline::Result<Vec<Option<ImageFeatures>>> {
        let conn = self.conn();
        let e = self.wrap();
        let mut ids = Vec::with_capacity(images.len());
        let mut out = Vec::with_capacity(images.len());
        let mut cache = self
            .keypoints
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        for path in images {
            let image = self.image(path)?;
            let row: Option<(i64, i64, i64)> = conn
                .query_row(
                    "SELECT i.image_id, c.width, c.height FROM images i JOIN cameras c ON i.camera_id = c.camera_id WHERE i.name = ?1",
                    params![image.name],
                    |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
                )
                .optional()
                .map_err(&e)?;
            let Some((id, w, h)) = row else {
                if self.map_only {
                    return Err(PosediffError::invalid(
                        &self.path,
                        format!(
                            "has no image {:?}: give --images the folder the database's names are relative to",
                            image.name
                        ),
                    ));
                }
                ids.push(-1);
                out.push(None);
                continue;
            };
            if !self.map_only {
                self.check_content(&conn, image)?;
            }
            ids.push(id);
            let kp: Option<(i64, i64, Vec<u8>)> = conn
                .query_row(
                    "SELECT rows, cols, data FROM keypoints WHERE image_id = ?1",
                    params![id],
                    |r| {
                        Ok((
                            r.get(0)?,
                            r.get(1)?,
                            r.get::<_, Option<Vec<u8>>>(2)?.unwrap_or_default(),
                        ))
                    },
                )
                .optional()
                .map_err(&e)?;
            let Some((rows, cols, kdata)) = kp else {
                if self.map_only {
                    return Err(PosediffError::invalid(
                        &self.path,
                        format!(
                            "has no keypoints of {:?}: extract its features first",
                            image.name
                        ),
                    ));
                }
                out.push(None);
                continue;
            };
            let keypoints = decode_keypoints(&self.path, rows as usize, cols as usize, &kdata)?;
            let descriptors = if self.map_only {
                // The mapper needs the keypoints only; the descriptors (any writer's) are not
                // read.
                Descriptors::Float {
                    data: Vec::new(),
                    dim: 0,
                }
            } else {
                let desc: Option<(i64, i64, i64, Vec<u8>)> = conn
                    .query_row(
                        "SELECT type, rows, cols, data FROM descriptors WHERE image_id = ?1",
                        params![id],
                        |r| {
                            Ok((
                                r.get(0)?,
                                r.get(1)?,
                                r.get(2)?,
                                r.get::<_, Option<Vec<u8>>>(3)?.unwrap_or_default(),
                            ))
                        },
                    )
                    .optional()
                    .map_err(&e)?;
                let Some((kind, drows, dcols, ddata)) = desc else {
                    out.push(None);
                    continue;
                };
                if drows != rows {
                    return Err(PosediffError::invalid(
                        &self.path,
                        format!(
                            "image {}: {rows} keypoints and {drows} descriptors",
                            image.name
                        ),
                    ));
                }
                self.decode_descriptors(kind, drows as usize, dcols as usize, &ddata)?
            };
            cache.insert(id, keypoints.clone());
            out.push(Some(ImageFeatures {
                image_size: ImageSize::new(w as u32, h as u32)?,
                keypoints,
                descriptors,
                half_turned: false,
            }));
        }
        *self
            .run
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = RunImages {
            index: images.iter().cloned().zip(0..).collect(),
            ids,
        };
        Ok(out)
    }

    fn put_features(
        &self,
        images: &[&Path],
        features: Vec<ImageFeatures>,
    ) -> posediff_pipeline::Result<Vec<ImageFeatures>> {
        self.writable()?;
        let mut conn = self.conn();
        let e = self.wrap();
        let tx = conn.transaction().map_err(&e)?;
        let mut out = Vec::with_capacity(features.len());
        let mut new_ids = Vec::with_capacity(features.len());
        for (path, f) in images.iter().zip(features) {
            let image = self.image(path)?;
            let (w, h) = (f.image_size.width(), f.image_size.height());
            let (fw, fh) = (f64::from(w), f64::from(h));
            // An image stored without keypoints (a worker's database whose features were
            // stripped, `posediff.distributed`; each image is otherwise written whole in one
            // commit) keeps its id, so that the pairs stored with it stay its pairs; its old
            // frame rows go, and its camera and rig where no other image has them.
            let old: Option<(i64, i64)> = tx
                .query_row(
                    "SELECT image_id, camera_id FROM images WHERE name = ?1",
                    params![image.name],
                    |r| Ok((r.get(0)?, r.get(1)?)),
                )
                .optional()
                .map_err(&e)?;
            if let Some((old_id, old_camera)) = old {
                tx.execute_batch(&format!(
                    "DELETE FROM frames WHERE frame_id IN (SELECT frame_id FROM frame_data WHERE data_id = {old_id} AND sensor_type = {SENSOR_CAMERA});
                     DELETE FROM frame_data WHERE data_id = {old_id} AND sensor_type = {SENSOR_CAMERA};
                     DELETE FROM images WHERE image_id = {old_id};
                     DELETE FROM rigs WHERE ref_sensor_id = {old_camera} AND ref_sensor_type = {SENSOR_CAMERA} AND NOT EXISTS (SELECT 1 FROM images WHERE camera_id = {old_camera});
                     DELETE FROM cameras WHERE camera_id = {old_camera} AND NOT EXISTS (SELECT 1 FROM images WHERE camera_id = {old_camera});"
                ))
                .map_err(&e)?;
            }
            // The camera its key and size share, where it is stored and still there.
            let store_key = image.camera.as_deref().map(|k| camera_store_key(k, w, h));
            let shared: Option<(i64, i64)> = match &store_key {
                Some(key) => tx
                    .query_row(
                        "SELECT c.camera_id, r.rig_id FROM posediff_store s JOIN cameras c ON c.camera_id = CAST(s.value AS INTEGER) JOIN rigs r ON r.ref_sensor_id = c.camera_id AND r.ref_sensor_type = ?2 WHERE s.key = ?1",
                        params![key, SENSOR_CAMERA],
                        |r| Ok((r.get(0)?, r.get(1)?)),
                    )
                    .optional()
                    .map_err(&e)?,
                None => None,
            };
            let (camera, rig) = match shared {
                Some(found) => found,
                None => {
                    let (focal, prior) = match image.focal.prior(w, h) {
                        Some((f, _)) => (f, 1),
                        None => (1.2 * fw.max(fh), 0),
                    };
                    tx.execute(
                        "INSERT INTO cameras (model, width, height, params, prior_focal_length) VALUES (?1, ?2, ?3, ?4, ?5)",
                        params![SIMPLE_RADIAL, i64::from(w), i64::from(h), f64_blob(&[focal, fw / 2.0, fh / 2.0, 0.0]), prior],
                    )
                    .map_err(&e)?;
                    let camera = tx.last_insert_rowid();
                    tx.execute(
                        "INSERT INTO rigs (ref_sensor_id, ref_sensor_type) VALUES (?1, ?2)",
                        params![camera, SENSOR_CAMERA],
                    )
                    .map_err(&e)?;
                    let rig = tx.last_insert_rowid();
                    if let Some(key) = &store_key {
                        tx.execute(
                            "INSERT OR REPLACE INTO posediff_store (key, value) VALUES (?1, ?2)",
                            params![key, camera.to_string()],
                        )
                        .map_err(&e)?;
                    }
                    (camera, rig)
                }
            };
            tx.execute(
                "INSERT INTO images (image_id, name, camera_id) VALUES (?1, ?2, ?3)",
                params![old.map(|(id, _)| id), image.name, camera],
            )
            .map_err(&e)?;
            let id = tx.last_insert_rowid();
            tx.execute(
                "INSERT OR REPLACE INTO posediff_store (key, value) VALUES (?1, ?2)",
                params![content_key(&image.name), content_digest(&image.path)?],
            )
            .map_err(&e)?;
            tx.execute("INSERT INTO frames (rig_id) VALUES (?1)", params![rig])
                .map_err(&e)?;
            let frame = tx.last_insert_rowid();
            tx.execute(
                "INSERT INTO frame_data (frame_id, data_id, sensor_id, sensor_type) VALUES (?1, ?2, ?3, ?4)",
                params![frame, id, camera, SENSOR_CAMERA],
            )
            .map_err(&e)?;
            let kdata: Vec<u8> = f
                .keypoints
                .iter()
                .flat_map(|k| {
                    [
                        (k[0] + PIXEL_CENTRE_OFFSET) as f32,
                        (k[1] + PIXEL_CENTRE_OFFSET) as f32,
                    ]
                })
                .flat_map(f32::to_le_bytes)
                .collect();
            let n = f.keypoints.len();
            tx.execute(
                "INSERT OR REPLACE INTO keypoints (image_id, rows, cols, data) VALUES (?1, ?2, 2, ?3)",
                params![id, n as i64, kdata],
            )
            .map_err(&e)?;
            let (kind, cols, ddata) = self.encode_descriptors(&f)?;
            tx.execute(
                "INSERT OR REPLACE INTO descriptors (image_id, type, rows, cols, data) VALUES (?1, ?2, ?3, ?4, ?5)",
                params![id, kind, n as i64, cols as i64, ddata],
            )
            .map_err(&e)?;
            // What a later run reads back.
            let keypoints = decode_keypoints(&self.path, n, 2, &kdata)?;
            let descriptors = self.decode_descriptors(kind, n, cols, &ddata)?;
            new_ids.push((path.to_path_buf(), id, keypoints.clone()));
            out.push(ImageFeatures {
                image_size: f.image_size,
                keypoints,
                descriptors,
                half_turned: false,
            });
        }
        tx.commit().map_err(&e)?;
        let mut cache = self
            .keypoints
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let mut run = self
            .run
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        for (path, id, kp) in new_ids {
            cache.insert(id, kp);
            // The run's list (set by `features`) learns the new id.
            if let Some(&slot) = run.index.get(&path) {
                run.ids[slot] = id;
            }
        }
        Ok(out)
    }

    fn matches(
        &self,
        pairs: &[(usize, usize)],
    ) -> posediff_pipeline::Result<Vec<Option<StoredMatches>>> {
        self.pair_rows("two_view_geometries", pairs)
    }

    fn put_matches(&self, pairs: &[PairMatches]) -> posediff_pipeline::Result<()> {
        self.put_matches_with_raw(pairs, &vec![None; pairs.len()])
    }

    fn put_matches_with_raw(
        &self,
        pairs: &[PairMatches],
        raw: &[Option<PairMatches>],
    ) -> posediff_pipeline::Result<()> {
        if raw.len() != pairs.len() {
            return Err(PosediffError::InvalidArgument(format!(
                "{} pairs of raw matches for {} pairs to store in {}",
                raw.len(),
                pairs.len(),
                self.path.display()
            )));
        }
        self.writable()?;
        let mut conn = self.conn();
        let e = self.wrap();
        let ids = self
            .run
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .ids
            .clone();
        let cache = self
            .keypoints
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let tx = conn.transaction().map_err(&e)?;
        for (p, raw) in pairs.iter().zip(raw) {
            let (a, b) = (run_id(&ids, p.first)?, run_id(&ids, p.second)?);
            if let Some(r) = raw
                && (r.first, r.second) != (p.first, p.second)
            {
                return Err(PosediffError::InvalidArgument(format!(
                    "raw matches of pair ({}, {}) given for pair ({}, {})",
                    r.first, r.second, p.first, p.second
                )));
            }
            let keypoints = (cache.get(&a), cache.get(&b));
            let (data, x1, x2) = stored_rows(p, a > b, keypoints);
            let raw_rows = raw
                .as_ref()
                .map(|r| (r.len(), stored_rows(r, a > b, keypoints).0));
            insert_pair(
                &tx,
                &e,
                pair_id(a as u32, b as u32),
                (p.len(), &data),
                raw_rows.as_ref().map(|(n, d)| (*n, d.as_slice())),
                (&x1, &x2),
            )?;
        }
        tx.commit().map_err(&e)?;
        Ok(())
    }

    fn fixed_pairs(&self) -> posediff_pipeline::Result<Option<Vec<(usize, usize)>>> {
        if !self.map_only {
            return Ok(None);
        }
        // Verified geometries with inliers (COLMAP's mappers skip the rest the same way).
        let pairs = self.pairs_where(&format!(
            "rows > 0 AND config NOT IN ({UNDEFINED}, {DEGENERATE}, {WATERMARK}, {MULTIPLE})"
        ))?;
        log::info!("{} verified pairs in {}", pairs.len(), self.path.display());
        Ok(Some(pairs))
    }

    fn selection(&self, rules: &str) -> posediff_pipeline::Result<Option<Vec<(usize, usize)>>> {
        let names = self.run_names();
        let e = self.wrap();
        let stored = store_value(&self.conn(), &format!("selection:{rules}")).map_err(&e)?;
        let Some(text) = stored else {
            return Ok(None);
        };
        let stored: StoredSelection = serde_json::from_str(&text).map_err(|err| {
            PosediffError::invalid(&self.path, format!("its stored selection {rules:?}: {err}"))
        })?;
        if stored.images != names {
            // Made for other images (or another order): made again.
            return Ok(None);
        }
        let n = names.len();
        if stored
            .pairs
            .iter()
            .any(|&(i, j)| i >= n || j >= n || i == j)
        {
            return Err(PosediffError::invalid(
                &self.path,
                format!("its stored selection {rules:?} names images it does not list"),
            ));
        }
        Ok(Some(stored.pairs))
    }

    fn put_selection(
        &self,
        rules: &str,
        pairs: &[(usize, usize)],
    ) -> posediff_pipeline::Result<()> {
        if self.map_only || self.source {
            return Ok(());
        }
        let value = serde_json::to_string(&StoredSelection {
            images: self.run_names(),
            pairs: pairs.to_vec(),
        })
        .map_err(|err| PosediffError::InvalidArgument(format!("selection {rules:?}: {err}")))?;
        let e = self.wrap();
        self.conn()
            .execute(
                "INSERT OR REPLACE INTO posediff_store (key, value) VALUES (?1, ?2)",
                params![format!("selection:{rules}"), value],
            )
            .map_err(&e)?;
        Ok(())
    }

    fn images(&self) -> usize {
        self.run
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .ids
            .len()
    }
}

/// The database id of the run's image `i` (which must have features stored).
fn run_id(ids: &[i64], i: usize) -> Result<i64> {
    match ids.get(i) {
        Some(&id) if id > 0 => Ok(id),
        _ => Err(PosediffError::InvalidArgument(format!(
            "image {i} has no features in the database"
        ))),
    }
}
