//! Per-image records (cameras.json entries, COLMAP images, ground truths) matched to the images
//! by name, never by position: the exact relative path first, then the file name where it is
//! unique on both sides. Whatever does not match is listed, so a file written for other images
//! (or another order) can never be applied silently.

use std::collections::HashMap;
use std::path::Path;

/// The outcome of [`match_by_name`].
#[derive(Debug, Clone, PartialEq)]
pub struct Matched<T> {
    /// One slot per image, in the images' order.
    pub per_image: Vec<Option<T>>,
    /// Images no record names.
    pub images_without_record: Vec<String>,
    /// Records that name no image.
    pub records_without_image: Vec<String>,
}

impl<T> Matched<T> {
    /// How many images have a record.
    pub fn matched(&self) -> usize {
        self.per_image.iter().filter(|r| r.is_some()).count()
    }

    /// Every image has a record and every record an image; else one message listing both
    /// sides (at most 10 names each).
    ///
    /// # Errors
    /// The message, starting with `what` and `file`.
    pub fn complete(self, what: &str, file: &Path) -> Result<Vec<T>, String> {
        if self.images_without_record.is_empty() && self.records_without_image.is_empty() {
            return Ok(self.per_image.into_iter().flatten().collect());
        }
        Err(self.mismatch(what, file))
    }

    /// The message of a mismatch.
    pub fn mismatch(&self, what: &str, file: &Path) -> String {
        let list = |v: &[String]| {
            let mut s = v.iter().take(10).cloned().collect::<Vec<_>>().join(", ");
            if v.len() > 10 {
                s.push_str(&format!(" and {} more", v.len() - 10));
            }
            s
        };
        let mut parts = Vec::new();
        if !self.images_without_record.is_empty() {
            parts.push(format!(
                "{} image(s) have no entry: {}",
                self.images_without_record.len(),
                list(&self.images_without_record)
            ));
        }
        if !self.records_without_image.is_empty() {
            parts.push(format!(
                "{} entr(y/ies) name no input image: {}",
                self.records_without_image.len(),
                list(&self.records_without_image)
            ));
        }
        format!(
            "{what} {} does not match the images by name ({}; entries are matched by relative path, then by file name)",
            file.display(),
            parts.join("; ")
        )
    }
}

fn file_name(s: &str) -> &str {
    Path::new(s)
        .file_name()
        .and_then(|f| f.to_str())
        .unwrap_or(s)
}

fn normalise(s: &str) -> &str {
    s.trim_start_matches("./")
}

/// Matches `records` (name, value) to `images` (names relative to the input folder).
///
/// # Errors
/// Two records for one image (named in the message).
pub fn match_by_name<T>(
    images: &[String],
    records: Vec<(String, T)>,
) -> Result<Matched<T>, String> {
    let exact: HashMap<&str, usize> = images
        .iter()
        .enumerate()
        .map(|(k, n)| (normalise(n), k))
        .collect();
    // File names that occur once among the images.
    let mut by_file: HashMap<&str, Option<usize>> = HashMap::new();
    for (k, n) in images.iter().enumerate() {
        by_file
            .entry(file_name(n))
            .and_modify(|e| *e = None)
            .or_insert(Some(k));
    }
    let mut record_files: HashMap<String, usize> = HashMap::new();
    for (name, _) in &records {
        *record_files.entry(file_name(name).to_owned()).or_default() += 1;
    }
    let mut per_image: Vec<Option<T>> = images.iter().map(|_| None).collect();
    let mut taken_by: Vec<Option<String>> = vec![None; images.len()];
    let mut records_without_image = Vec::new();
    for (name, value) in records {
        let slot = exact.get(normalise(&name)).copied().or_else(|| {
            let f = file_name(&name);
            (record_files.get(f) == Some(&1))
                .then(|| by_file.get(f).copied().flatten())
                .flatten()
        });
        match slot {
            Some(k) => {
                if let Some(first) = &taken_by[k] {
                    return Err(format!(
                        "entries {first:?} and {name:?} both name image {}",
                        images[k]
                    ));
                }
                taken_by[k] = Some(name);
                per_image[k] = Some(value);
            }
            None => records_without_image.push(name),
        }
    }
    let images_without_record = images
        .iter()
        .zip(&per_image)
        .filter(|(_, r)| r.is_none())
        .map(|(n, _)| n.clone())
        .collect();
    Ok(Matched {
        per_image,
        images_without_record,
        records_without_image,
    })
}

/// The ground truth's cameras for the images `names`, matched by name: every image must have
/// one and every ground-truth camera an image (`what` names the estimate in the message).
///
/// # Errors
/// An unreadable ground truth; names that do not match both ways.
pub fn ground_truth_for(
    names: &[String],
    gt: &Path,
    what: &str,
) -> crate::Result<Vec<posediff_geometry::Camera>> {
    let truth = crate::io::export::read_cameras_json(gt)?;
    match_by_name(
        names,
        truth
            .into_iter()
            .map(|c| (c.image.clone(), c.camera))
            .collect(),
    )
    .map_err(|e| crate::PosediffError::invalid(gt, format!("--gt: {e}")))?
    .complete(&format!("--gt (for {what})"), gt)
    .map_err(|e| crate::PosediffError::invalid(gt, e))
}

/// The cameras of a COLMAP model for the images of a folder, in the folder's order, matched
/// by name ([`match_by_name`]): an image COLMAP did not register is not estimated.
///
/// # Errors
/// An unreadable model; a model none of whose images is in the folder, or whose images name
/// the folder's only ambiguously; an image of the folder that cannot be read for its size.
pub fn colmap_for_images(
    model: &Path,
    images: &[std::path::PathBuf],
    root: &Path,
) -> crate::Result<Vec<crate::reconstruction::ImageCamera>> {
    let colmap = crate::io::colmap::ColmapModel::read(model)?;
    let cams = colmap.named_cameras(model)?;
    // Each registered image's lens (a distorting model: SIMPLE_RADIAL, OPENCV, …).
    let lenses: std::collections::HashMap<String, posediff_geometry::lens::LensCamera> = colmap
        .images
        .iter()
        .zip(colmap.image_lenses(model)?)
        .filter_map(|(im, lens)| lens.map(|l| (im.name.clone(), l)))
        .collect();
    let names: Vec<String> = images
        .iter()
        .map(|p| crate::io::loader::relative_name(p, Some(root)))
        .collect();
    let matched = match_by_name(
        &names,
        cams.into_iter()
            .map(|c| (c.image.clone(), c.camera))
            .collect(),
    )
    .map_err(|e| crate::PosediffError::invalid(model, e))?;
    if matched.matched() == 0 && !names.is_empty() {
        return Err(crate::PosediffError::invalid(
            model,
            matched.mismatch("the COLMAP model", model),
        ));
    }
    if !matched.records_without_image.is_empty() {
        log::warn!(
            "{}: {} registered image(s) are not in {}: {}",
            model.display(),
            matched.records_without_image.len(),
            root.display(),
            matched.records_without_image.join(", ")
        );
    }
    images
        .iter()
        .zip(names)
        .zip(matched.per_image)
        .map(|((path, name), camera)| match camera {
            Some(c) => Ok(crate::reconstruction::ImageCamera {
                lens: lenses.get(&name).cloned(),
                image: name,
                size: c.image_size,
                camera: Some(c),
            }),
            None => {
                let img = crate::reconstruction::read_colour(path)?;
                Ok(crate::reconstruction::ImageCamera {
                    image: name,
                    size: crate::reconstruction::mat_size(&img, path)?,
                    camera: None,
                    lens: None,
                })
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn names(v: &[&str]) -> Vec<String> {
        v.iter().map(|s| (*s).to_owned()).collect()
    }

    #[test]
    fn records_in_any_order_land_on_their_images() {
        let images = names(&["a.jpg", "b.jpg", "sub/c.jpg"]);
        let records = vec![
            ("images/c.jpg".to_owned(), 3),
            ("a.jpg".to_owned(), 1),
            ("./b.jpg".to_owned(), 2),
        ];
        let m = match_by_name(&images, records).unwrap();
        assert_eq!(m.per_image, vec![Some(1), Some(2), Some(3)]);
        assert!(m.images_without_record.is_empty() && m.records_without_image.is_empty());
    }

    #[test]
    fn ambiguous_file_names_need_the_exact_path() {
        let images = names(&["x/a.jpg", "y/a.jpg"]);
        let m = match_by_name(&images, vec![("z/a.jpg".to_owned(), 0)]).unwrap();
        assert_eq!(m.matched(), 0);
        assert_eq!(m.records_without_image, names(&["z/a.jpg"]));
        let m = match_by_name(&images, vec![("y/a.jpg".to_owned(), 0)]).unwrap();
        assert_eq!(m.per_image, vec![None, Some(0)]);
    }

    #[test]
    fn mismatches_are_listed_and_duplicates_refused() {
        let images = names(&["a.jpg", "b.jpg"]);
        let m = match_by_name(
            &images,
            vec![("a.jpg".to_owned(), 0), ("q.jpg".to_owned(), 1)],
        )
        .unwrap();
        let e = m.complete("--intrinsics", Path::new("k.json")).unwrap_err();
        assert!(
            e.contains("b.jpg") && e.contains("q.jpg") && e.contains("k.json"),
            "{e}"
        );
        let e = match_by_name(
            &images,
            vec![("a.jpg".to_owned(), 0), ("./a.jpg".to_owned(), 1)],
        )
        .unwrap_err();
        assert!(e.contains("both name image a.jpg"), "{e}");
    }
}
