//! `--database`, `posediff features`, `posediff match`, `posediff map`: COLMAP's database as
//! the store of a run, on the real fountain images (11 photos, 55 pairs).
//!
//! - A `posediff match` killed (SIGKILL) mid-matching leaves a database that SQLite recovers
//!   and the next run resumes from: its log says how many pairs it found stored, and its
//!   cameras are byte-identical to an uninterrupted run's.
//! - A second writer is refused while a run holds the database; a run with another matcher
//!   is refused instead of mixing features.
//! - `posediff map` gives the same cameras from the database alone.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::ffi::OsStr;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Output, Stdio};

use posediff_fixtures::shared_path;

fn posediff(args: &[&OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_posediff"))
        .args(args)
        .env("RUST_LOG", "posediff=info,posediff_pipeline=info")
        .output()
        .unwrap()
}

fn ok(args: &[&OsStr]) -> Output {
    let out = posediff(args);
    assert!(
        out.status.success(),
        "posediff {:?}: {}",
        args,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn stored_pairs(db: &Path) -> (i64, i64) {
    let c = rusqlite::Connection::open(db).unwrap();
    c.query_row(
        "SELECT count(*), coalesce(sum(rows > 0), 0) FROM two_view_geometries",
        [],
        |r| Ok((r.get(0)?, r.get(1)?)),
    )
    .unwrap()
}

#[test]
fn an_interrupted_match_resumes_to_the_same_cameras() {
    let dir = posediff_fixtures::temp_dir("database-resume");
    let images = shared_path("data/strecha_fountainP11/images");
    let db = dir.join("d.db");
    // Matching in commits of 4 pairs, killed after the first commit.
    let mut child = Command::new(env!("CARGO_BIN_EXE_posediff"))
        .args([
            "match".as_ref(),
            images.as_os_str(),
            "--database".as_ref(),
            db.as_os_str(),
            "--pairs".as_ref(),
            "exhaustive".as_ref(),
            "--set".as_ref(),
            "database.pairs_per_commit=4".as_ref(),
            "--quiet".as_ref(),
        ])
        .env("RUST_LOG", "posediff=info,posediff_pipeline=info")
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    let mut log = String::new();
    loop {
        let line = lines
            .next()
            .unwrap_or_else(|| panic!("posediff match ended before storing pairs:\n{log}"))
            .unwrap();
        log.push_str(&line);
        log.push('\n');
        if line.contains("matching: stored") {
            break;
        }
    }
    // While it runs, a second writer is refused, naming the database.
    let second = posediff(&[
        "features".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        db.as_os_str(),
        "--quiet".as_ref(),
    ]);
    let err = String::from_utf8_lossy(&second.stderr);
    assert!(!second.status.success());
    assert!(
        err.contains("in use by another process") && err.contains("d.db"),
        "{err}"
    );
    child.kill().unwrap();
    assert!(!child.wait().unwrap().success(), "the run was not killed");
    let (kept, _) = stored_pairs(&db);
    assert!(kept > 0 && kept < 55, "{kept} pairs stored before the kill");
    // The next run resumes: every image and the stored pairs come from the database.
    let out1 = dir.join("resumed");
    let resumed = ok(&[
        "estimate".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        db.as_os_str(),
        "--pairs".as_ref(),
        "exhaustive".as_ref(),
        "--out".as_ref(),
        out1.as_os_str(),
        "--no-view".as_ref(),
        "--quiet".as_ref(),
    ]);
    let log = String::from_utf8_lossy(&resumed.stderr);
    assert!(
        log.contains("features: 11 of 11 images from the database, 0 to extract"),
        "{log}"
    );
    assert!(
        log.contains(&format!(
            "matching: {kept} of 55 pairs from the database, {} to match",
            55 - kept
        )),
        "{log}"
    );
    assert_eq!(stored_pairs(&db).0, 55);
    // An uninterrupted run into a new database gives the same bytes.
    let db2 = dir.join("d2.db");
    let out2 = dir.join("whole");
    ok(&[
        "estimate".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        db2.as_os_str(),
        "--pairs".as_ref(),
        "exhaustive".as_ref(),
        "--out".as_ref(),
        out2.as_os_str(),
        "--no-view".as_ref(),
        "--quiet".as_ref(),
    ]);
    let cameras = |d: &Path| std::fs::read(d.join("cameras.json")).unwrap();
    assert_eq!(
        cameras(&out1),
        cameras(&out2),
        "resumed and whole runs differ"
    );
    assert_eq!(stored_pairs(&db), stored_pairs(&db2));
    // The same run split over three workers (`--shard`), each into its own database, merged by
    // a driver (`--from`): the same pairs and the same bytes.
    let part = |stage: &str, db: &Path, shard: &str, from: &[&Path]| {
        let mut args: Vec<&OsStr> = vec![
            stage.as_ref(),
            images.as_os_str(),
            "--database".as_ref(),
            db.as_os_str(),
            "--pairs".as_ref(),
            "exhaustive".as_ref(),
            "--shard".as_ref(),
            shard.as_ref(),
        ];
        for f in from {
            args.extend(["--from".as_ref(), f.as_os_str()]);
        }
        ok(&args)
    };
    let extracted: Vec<_> = (0..3).map(|k| dir.join(format!("f{k}.db"))).collect();
    for (k, f) in extracted.iter().enumerate() {
        let out = part("features", f, &format!("{k}/3"), &[]);
        let said = String::from_utf8_lossy(&out.stdout);
        let n = [3, 4, 4][k];
        assert!(
            said.contains(&format!("{n} images with features")),
            "{said}"
        );
    }
    let merged = dir.join("merged.db");
    let mut args: Vec<&OsStr> = vec![
        "features".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        merged.as_os_str(),
    ];
    for f in &extracted {
        args.extend(["--from".as_ref(), f.as_os_str()]);
    }
    let said = ok(&args);
    assert!(
        String::from_utf8_lossy(&said.stdout)
            .contains("imported 11 images' features and 0 pairs from 3 database(s)"),
        "{}",
        String::from_utf8_lossy(&said.stdout)
    );
    // The driver selects the pairs once; each worker matches its share of that selection.
    let said = ok(&[
        "match".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        merged.as_os_str(),
        "--pairs".as_ref(),
        "exhaustive".as_ref(),
        "--select-only".as_ref(),
    ]);
    assert!(
        String::from_utf8_lossy(&said.stdout).contains("55 pairs (exhaustive) selected, stored in"),
        "{}",
        String::from_utf8_lossy(&said.stdout)
    );
    assert_eq!(stored_pairs(&merged), (0, 0), "--select-only matched");
    let matched: Vec<_> = (0..3).map(|k| dir.join(format!("m{k}.db"))).collect();
    for (k, m) in matched.iter().enumerate() {
        let out = part("match", m, &format!("{k}/3"), &[&merged]);
        let said = String::from_utf8_lossy(&out.stdout);
        assert!(
            said.contains(&format!("pairs (exhaustive,shard:{k}/3) matched")),
            "{said}"
        );
        let log = String::from_utf8_lossy(&out.stderr);
        assert!(
            log.contains("selection: 55 pairs (exhaustive) from the database"),
            "{log}"
        );
    }
    let out4 = dir.join("sharded");
    let mut args: Vec<&OsStr> = vec![
        "estimate".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        merged.as_os_str(),
        "--pairs".as_ref(),
        "exhaustive".as_ref(),
        "--out".as_ref(),
        out4.as_os_str(),
        "--no-view".as_ref(),
        "--quiet".as_ref(),
    ];
    for m in &matched {
        args.extend(["--from".as_ref(), m.as_os_str()]);
    }
    let sharded = ok(&args);
    let log = String::from_utf8_lossy(&sharded.stderr);
    assert!(
        log.contains("matching: 55 of 55 pairs from the database, 0 to match"),
        "{log}"
    );
    assert_eq!(
        cameras(&out4),
        cameras(&out2),
        "sharded and whole runs differ"
    );
    assert_eq!(stored_pairs(&merged), stored_pairs(&db2));
    // A worker's database is only read; one of another matcher is refused, named.
    let orb_db = dir.join("orb.db");
    ok(&[
        "features".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        orb_db.as_os_str(),
        "--matcher".as_ref(),
        "orb".as_ref(),
        "--shard".as_ref(),
        "0/5".as_ref(),
        "--quiet".as_ref(),
    ]);
    let mixed = posediff(&[
        "features".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        merged.as_os_str(),
        "--from".as_ref(),
        orb_db.as_os_str(),
        "--quiet".as_ref(),
    ]);
    let err = String::from_utf8_lossy(&mixed.stderr);
    assert!(!mixed.status.success());
    assert!(
        err.contains("orb.db") && err.contains("holds features made with matcher orb"),
        "{err}"
    );
    // `posediff map` maps the database's verified pairs to the same cameras.
    let out3 = dir.join("mapped");
    ok(&[
        "map".as_ref(),
        "--database".as_ref(),
        db.as_os_str(),
        "--images".as_ref(),
        images.as_os_str(),
        "--out".as_ref(),
        out3.as_os_str(),
        "--no-view".as_ref(),
        "--quiet".as_ref(),
    ]);
    assert_eq!(cameras(&out1), cameras(&out3), "map and estimate differ");
    // Another matcher's features are not mixed in.
    let orb = posediff(&[
        "match".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        db.as_os_str(),
        "--matcher".as_ref(),
        "orb".as_ref(),
        "--quiet".as_ref(),
    ]);
    let err = String::from_utf8_lossy(&orb.stderr);
    assert!(!orb.status.success());
    assert!(
        err.contains("holds features made with matcher sift") && err.contains("orb"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Every pair's matches by image names, as (keypoint of the first name, of the second).
fn matches_by_name(db: &Path) -> std::collections::BTreeMap<(String, String), Vec<(u32, u32)>> {
    rows_by_name(db, "matches")
}

/// [`matches_by_name`] of `table` (`matches` or `two_view_geometries`).
fn rows_by_name(
    db: &Path,
    table: &str,
) -> std::collections::BTreeMap<(String, String), Vec<(u32, u32)>> {
    let c = rusqlite::Connection::open(db).unwrap();
    let names: std::collections::HashMap<i64, String> = c
        .prepare("SELECT image_id, name FROM images")
        .unwrap()
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
        .unwrap()
        .map(Result::unwrap)
        .collect();
    let mut stmt = c
        .prepare(&format!("SELECT pair_id, data FROM {table}"))
        .unwrap();
    let rows: Vec<(i64, Option<Vec<u8>>)> = stmt
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
        .unwrap()
        .map(Result::unwrap)
        .collect();
    rows.into_iter()
        .map(|(id, data)| {
            let (a, b) = (&names[&(id / 2_147_483_647)], &names[&(id % 2_147_483_647)]);
            let words: Vec<u32> = data
                .unwrap_or_default()
                .chunks_exact(4)
                .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
                .collect();
            let mut m: Vec<(u32, u32)> = words
                .chunks_exact(2)
                .map(|p| if a < b { (p[0], p[1]) } else { (p[1], p[0]) })
                .collect();
            m.sort_unstable();
            ((a.min(b).clone(), a.max(b).clone()), m)
        })
        .collect()
}

/// A worker that listed the images in another order holds each pair the other way round
/// (COLMAP orders a pair by image id): importing it turns every pair's matches round.
#[test]
fn a_worker_with_other_image_ids_imports_its_pairs_turned() {
    let dir = posediff_fixtures::temp_dir("database-reordered");
    let images = shared_path("data/strecha_fountainP11/images");
    let files: Vec<std::path::PathBuf> =
        (0..4).map(|k| images.join(format!("000{k}.jpg"))).collect();
    let worker = dir.join("w.db");
    let mut args: Vec<&OsStr> = vec!["match".as_ref()];
    args.extend(files.iter().rev().map(|f| f.as_os_str()));
    args.extend([
        "--database".as_ref(),
        worker.as_os_str(),
        "--pairs".as_ref(),
        "exhaustive".as_ref(),
        "--quiet".as_ref(),
    ]);
    ok(&args);
    let merged = dir.join("m.db");
    let mut args: Vec<&OsStr> = vec!["match".as_ref()];
    args.extend(files.iter().map(|f| f.as_os_str()));
    args.extend([
        "--database".as_ref(),
        merged.as_os_str(),
        "--pairs".as_ref(),
        "exhaustive".as_ref(),
        "--from".as_ref(),
        worker.as_os_str(),
    ]);
    let out = ok(&args);
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("imported 4 images' features and 6 pairs"),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    assert!(
        log.contains("matching: 6 of 6 pairs from the database, 0 to match"),
        "{log}"
    );
    // The worker's stored selection came in with its pairs, but it was made for the images in
    // the other order: it is made again, not used.
    assert!(!log.contains("selection: 6 pairs"), "{log}");
    let theirs = matches_by_name(&worker);
    assert_eq!(theirs.len(), 6);
    // `matches` holds each pair's matches before verification, `two_view_geometries` the
    // verified ones among them (COLMAP's layout); SIFT's mutual nearest neighbours on the
    // fountain include outliers MAGSAC drops.
    let verified = rows_by_name(&worker, "two_view_geometries");
    assert_eq!(verified.len(), 6);
    for (pair, inliers) in &verified {
        let raw: std::collections::BTreeSet<&(u32, u32)> = theirs[pair].iter().collect();
        assert!(inliers.iter().all(|m| raw.contains(m)), "{pair:?}");
        assert!(raw.len() > inliers.len(), "{pair:?}: {} raw", raw.len());
    }
    assert_eq!(rows_by_name(&merged, "two_view_geometries"), verified);
    assert_eq!(matches_by_name(&merged), theirs);
    // The ids run the other way in the two databases.
    let first_id = |db: &Path| -> i64 {
        rusqlite::Connection::open(db)
            .unwrap()
            .query_row(
                "SELECT image_id FROM images WHERE name = '0000.jpg'",
                [],
                |r| r.get(0),
            )
            .unwrap()
    };
    assert_eq!((first_id(&worker), first_id(&merged)), (4, 1));
    assert_eq!(stored_pairs(&merged), stored_pairs(&worker));
    // An image whose features were stripped (as posediff.distributed strips a matching task's
    // database) is extracted again under its old id: its stored pairs stay its pairs.
    let id_of = |name: &str| -> i64 {
        rusqlite::Connection::open(&merged)
            .unwrap()
            .query_row("SELECT image_id FROM images WHERE name = ?1", [name], |r| {
                r.get(0)
            })
            .unwrap()
    };
    let before = id_of("0001.jpg");
    {
        let c = rusqlite::Connection::open(&merged).unwrap();
        c.execute_batch(&format!(
            "DELETE FROM keypoints WHERE image_id = {before}; DELETE FROM descriptors WHERE image_id = {before};"
        ))
        .unwrap();
    }
    let mut args: Vec<&OsStr> = vec!["match".as_ref()];
    args.extend(files.iter().map(|f| f.as_os_str()));
    args.extend([
        "--database".as_ref(),
        merged.as_os_str(),
        "--pairs".as_ref(),
        "exhaustive".as_ref(),
    ]);
    let log = String::from_utf8_lossy(&ok(&args).stderr).into_owned();
    assert!(
        log.contains("features: 3 of 4 images from the database, 1 to extract")
            && log.contains("selection: 6 pairs (exhaustive) from the database")
            && log.contains("matching: 6 of 6 pairs from the database, 0 to match"),
        "{log}"
    );
    assert_eq!(id_of("0001.jpg"), before);
    assert_eq!(matches_by_name(&merged), theirs);
    let c = rusqlite::Connection::open(&merged).unwrap();
    let count = |sql: &str| -> i64 { c.query_row(sql, [], |r| r.get(0)).unwrap() };
    for table in [
        "images",
        "cameras",
        "rigs",
        "frames",
        "frame_data",
        "keypoints",
    ] {
        assert_eq!(
            count(&format!("SELECT count(*) FROM {table}")),
            4,
            "{table}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Bad databases fail before any work, naming the file and the fix.
#[test]
fn bad_databases_are_named_errors() {
    let dir = posediff_fixtures::temp_dir("database-bad");
    let images = shared_path("data/strecha_fountainP11/images");
    let text = dir.join("notes.db");
    std::fs::write(&text, "not a database, just some text that is long enough").unwrap();
    let cases: [(&Path, &str); 3] = [
        (&text, "is not a SQLite database"),
        (&dir.join("missing/d.db"), "its folder does not exist"),
        (&dir, "is a folder"),
    ];
    for (db, why) in cases {
        let out = posediff(&[
            "features".as_ref(),
            images.as_os_str(),
            "--database".as_ref(),
            db.as_os_str(),
            "--quiet".as_ref(),
        ]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{}", db.display());
        assert!(err.contains(why), "{}: {err}", db.display());
        assert!(!err.contains("stage: "), "work started: {err}");
    }
    // `map` of a database without the images named.
    let other = shared_path("data/middlebury_templeSR/images");
    let db = dir.join("f.db");
    ok(&[
        "features".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        db.as_os_str(),
        "--quiet".as_ref(),
    ]);
    let out = posediff(&[
        "map".as_ref(),
        "--database".as_ref(),
        db.as_os_str(),
        "--images".as_ref(),
        other.as_os_str(),
        "--out".as_ref(),
        dir.join("o").as_os_str(),
        "--quiet".as_ref(),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("has no image"), "{err}");
    // Shards and sources that cannot be used fail before any work, named.
    let missing = dir.join("w9.db");
    let new = dir.join("n.db");
    let cases: [(Vec<&OsStr>, &str); 4] = [
        (
            vec!["--shard".as_ref(), "3/3".as_ref()],
            "give K/N with 0 <= K < N",
        ),
        (vec!["--shard".as_ref(), "two".as_ref()], "give K/N"),
        (vec!["--from".as_ref(), missing.as_os_str()], "w9.db"),
        (
            vec!["--from".as_ref(), new.as_os_str()],
            "names the --database itself",
        ),
    ];
    for (extra, why) in cases {
        let mut args: Vec<&OsStr> = vec![
            "match".as_ref(),
            images.as_os_str(),
            "--database".as_ref(),
            new.as_os_str(),
            "--quiet".as_ref(),
        ];
        args.extend(extra);
        let out = posediff(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert!(err.contains(why), "{args:?}: {err}");
        assert!(!err.contains("stage: "), "work started: {err}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The store keeps each photo's content digest: a photo replaced under the same name is
/// refused by name (its stored features are another photo's), while the same bytes copied
/// again (a new modification time) resume as before.
#[test]
fn a_photo_replaced_under_its_name_is_refused() {
    let dir = posediff_fixtures::temp_dir("database-replaced");
    let set = shared_path("data/strecha_fountainP11/images");
    let mut names: Vec<std::path::PathBuf> = std::fs::read_dir(&set)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    names.sort();
    let images = dir.join("images");
    std::fs::create_dir_all(&images).unwrap();
    for p in &names[..3] {
        std::fs::copy(p, images.join(p.file_name().unwrap())).unwrap();
    }
    let db = dir.join("d.db");
    let features = || {
        posediff(&[
            "features".as_ref(),
            images.as_os_str(),
            "--database".as_ref(),
            db.as_os_str(),
            "--quiet".as_ref(),
        ])
    };
    assert!(features().status.success());
    // The same bytes again: resumed, nothing to extract.
    let first = images.join(names[0].file_name().unwrap());
    std::fs::copy(&names[0], &first).unwrap();
    let again = features();
    assert!(
        again.status.success(),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
    // Another photo under the first one's name.
    std::fs::copy(&names[5], &first).unwrap();
    let out = features();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    let name = names[0].file_name().unwrap().to_string_lossy();
    assert!(
        err.contains(name.as_ref()) && err.contains("was replaced") && err.contains("sha256:"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `posediff features --camera-mode single`: every photo of one size shares one COLMAP camera
/// and rig (a frame each), also when the photos come from two workers' databases (`--shard`,
/// `--from`) and when a run resumes a database that holds some of them; `per-image` gives each
/// its own.
#[test]
fn photos_share_one_camera_in_single_mode() {
    let dir = posediff_fixtures::temp_dir("database-single-camera");
    let images = shared_path("data/strecha_fountainP11/images");
    let features = |db: &Path, mode: &str, extra: &[&OsStr]| {
        let mut args: Vec<&OsStr> = vec![
            "features".as_ref(),
            images.as_os_str(),
            "--database".as_ref(),
            db.as_os_str(),
            "--camera-mode".as_ref(),
            mode.as_ref(),
            "--quiet".as_ref(),
        ];
        args.extend_from_slice(extra);
        ok(&args);
    };
    let counts = |db: &Path| -> (i64, i64, i64, i64) {
        let c = rusqlite::Connection::open(db).unwrap();
        c.query_row(
            "SELECT (SELECT count(*) FROM images), (SELECT count(*) FROM cameras), \
             (SELECT count(*) FROM rigs), (SELECT count(*) FROM frames)",
            [],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
        )
        .unwrap()
    };
    let (w0, w1, merged) = (dir.join("w0.db"), dir.join("w1.db"), dir.join("merged.db"));
    features(&w0, "single", &["--shard".as_ref(), "0/2".as_ref()]);
    features(&w1, "single", &["--shard".as_ref(), "1/2".as_ref()]);
    let (a, b) = (counts(&w0), counts(&w1));
    assert_eq!((a.1, a.2, b.1, b.2), (1, 1, 1, 1), "{a:?} {b:?}");
    assert_eq!(a.0 + b.0, 11);
    features(
        &merged,
        "single",
        &[
            "--from".as_ref(),
            w0.as_os_str(),
            "--from".as_ref(),
            w1.as_os_str(),
        ],
    );
    assert_eq!(counts(&merged), (11, 1, 1, 11));
    // Resumed: a database holding the first worker's photos gets the rest on the same camera.
    std::fs::copy(&w0, dir.join("resumed.db")).unwrap();
    features(&dir.join("resumed.db"), "single", &[]);
    assert_eq!(counts(&dir.join("resumed.db")), (11, 1, 1, 11));
    let per_image = dir.join("per-image.db");
    features(&per_image, "per-image", &[]);
    assert_eq!(counts(&per_image), (11, 11, 11, 11));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--weights W --database D`: GGS's features and matches (the checkpoint path's own
/// matching) go into the database; the cameras are those of the same run without it, a second
/// run reads every image and pair back and gives the same cameras, and the checkpoint-free
/// path (other matching settings) is refused on that database instead of mixing features, and
/// so is `--no-ggs` (no matching to store).
#[test]
fn the_network_path_keeps_its_matches_in_the_database() {
    let dir = posediff_fixtures::temp_dir("database-network");
    let images = shared_path("data/strecha_fountainP11/images");
    let weights = shared_path("reference/tiny/model_tiny.safetensors");
    let db = dir.join("ggs.db");
    let run = |out: &str, database: bool| {
        let out = dir.join(out);
        let mut args: Vec<&OsStr> = vec![
            "estimate".as_ref(),
            images.as_os_str(),
            "--weights".as_ref(),
            weights.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
            "--no-view".as_ref(),
        ];
        if database {
            args.extend(["--database".as_ref(), db.as_os_str()]);
        }
        let log = String::from_utf8_lossy(&ok(&args).stderr).into_owned();
        (std::fs::read(out.join("cameras.json")).unwrap(), log)
    };
    let (plain, _) = run("plain", false);
    let (first, _) = run("first", true);
    assert!(plain == first, "the database changed the cameras");
    let (pairs, verified) = stored_pairs(&db);
    assert_eq!(pairs, 55);
    assert!(verified >= 10, "{verified} verified pairs");
    let (second, log) = run("second", true);
    assert!(
        log.contains("11 of 11 images from the database") && log.contains("55 of 55 pairs"),
        "{log}"
    );
    assert!(second == first, "the cameras from the database differ");
    let refused = posediff(&[
        "estimate".as_ref(),
        images.as_os_str(),
        "--database".as_ref(),
        db.as_os_str(),
        "--out".as_ref(),
        dir.join("geometric").as_os_str(),
        "--quiet".as_ref(),
    ]);
    assert!(!refused.status.success());
    let e = String::from_utf8_lossy(&refused.stderr);
    assert!(e.contains("holds features made with settings"), "{e}");
    // --no-ggs skips matching: a database there is refused by name before any work.
    let no_ggs = posediff(&[
        "estimate".as_ref(),
        images.as_os_str(),
        "--weights".as_ref(),
        weights.as_os_str(),
        "--no-ggs".as_ref(),
        "--database".as_ref(),
        db.as_os_str(),
        "--out".as_ref(),
        dir.join("no-ggs").as_os_str(),
        "--quiet".as_ref(),
    ]);
    assert!(!no_ggs.status.success());
    let e = String::from_utf8_lossy(&no_ggs.stderr);
    assert!(e.contains("--no-ggs") && e.contains("ggs.db"), "{e}");
    assert!(!dir.join("no-ggs").join("cameras.json").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}
