//! The official `MultiScaleImageFeatureExtractor`: ImageNet normalisation, the ViT at scales
//! 1, 1/2 and 1/3 (bilinear `scale_factor` resizes: 224 → 224, 112, 74 px), features averaged.

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use crate::error::{DiffusionError, Result};
use crate::resize::{bilinear_matrix, scaled_len};
use crate::vit::{VisionTransformer, matrix, resize_separable};

/// ImageNet mean (`_resnet_mean`).
pub const IMAGENET_MEAN: [f64; 3] = [0.485, 0.456, 0.406];
/// ImageNet standard deviation (`_resnet_std`).
pub const IMAGENET_STD: [f64; 3] = [0.229, 0.224, 0.225];
/// The official `scale_factors`.
pub const SCALE_FACTORS: [f64; 3] = [1.0, 1.0 / 2.0, 1.0 / 3.0];

/// Image features for the denoiser.
#[derive(Debug, Clone)]
pub struct ImageFeatureExtractor {
    vit: VisionTransformer,
}

impl ImageFeatureExtractor {
    /// Loads the ViT with `depth` blocks from `vb` at the root of the state dict.
    ///
    /// # Errors
    /// Missing or mis-shaped weights.
    pub fn new(depth: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            vit: VisionTransformer::new(depth, vb.pp("image_feature_extractor").pp("_net"))?,
        })
    }

    /// The ViT.
    pub fn vit(&self) -> &VisionTransformer {
        &self.vit
    }

    /// `(x − mean) / std` per channel, for `(N, 3, H, W)` images in `[0, 1]`.
    ///
    /// # Errors
    /// Wrong shape.
    pub fn normalize(&self, images: &Tensor) -> Result<Tensor> {
        let dims = images.dims().to_vec();
        if dims.len() != 4 || dims[1] != 3 {
            return Err(DiffusionError::Shape {
                what: "images",
                expected: "(N, 3, H, W)",
                got: dims,
            });
        }
        let (dtype, device) = (images.dtype(), images.device());
        let channel = |v: [f64; 3]| -> Result<Tensor> {
            Ok(Tensor::from_vec(v.to_vec(), (1, 3, 1, 1), device)?.to_dtype(dtype)?)
        };
        Ok(images
            .broadcast_sub(&channel(IMAGENET_MEAN)?)?
            .broadcast_div(&channel(IMAGENET_STD)?)?)
    }

    /// `F.interpolate(x, scale_factor=s, mode="bilinear", align_corners=False)`.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn resize(&self, x: &Tensor, scale_factor: f64) -> Result<Tensor> {
        let (n, c, h, w) = x.dims4()?;
        let (ho, wo) = (scaled_len(h, scale_factor), scaled_len(w, scale_factor));
        let (dtype, device): (DType, &Device) = (x.dtype(), x.device());
        let m_h = matrix(bilinear_matrix(h, ho, scale_factor), ho, h, dtype, device)?;
        let m_w = matrix(bilinear_matrix(w, wo, scale_factor), wo, w, dtype, device)?;
        let flat = x.reshape((n * c, h, w))?;
        Ok(resize_separable(&flat, &m_h, &m_w)?.reshape((n, c, ho, wo))?)
    }

    /// The ViT output at each scale, for normalised images, each scale in a pass of its own
    /// (what [`Self::forward`]'s one stacked pass is checked against).
    ///
    /// # Errors
    /// Tensor errors.
    pub fn per_scale(&self, normalized: &Tensor) -> Result<Vec<Tensor>> {
        SCALE_FACTORS
            .iter()
            .map(|&s| {
                if s == 1.0 {
                    self.vit.forward(normalized)
                } else {
                    self.vit.forward(&self.resize(normalized, s)?)
                }
            })
            .collect()
    }

    /// Most images per pass through the ViT. The features of each image are independent;
    /// passes of at most 10 keep every activation under mimalloc's 16 MiB large-object limit
    /// (a pass stacks the three scales' `197 + 50 + 17` tokens per image: the MLP's
    /// `10 × 264 × 1536` floats are 16.2 MB, 16 MiB is 16.8 MB), so the allocator reuses the
    /// buffers instead of mapping fresh pages for each layer (one batch of 100 images spent
    /// 16 % of its time in the kernel zeroing them, and peaked at twice the memory), while the
    /// products keep over 1,500 rows (the linear layers' full speed from about 800).
    pub const MAX_IMAGES_PER_PASS: usize = 10;

    /// The averaged features `(N, 384)` of `(N, 3, H, W)` images in `[0, 1]` (the official
    /// input is 224×224).
    ///
    /// # Errors
    /// Wrong shape, tensor errors.
    pub fn forward(&self, images: &Tensor) -> Result<Tensor> {
        let n = images.dim(0)?;
        if n > Self::MAX_IMAGES_PER_PASS {
            // Passes of equal size (within one), none above the maximum.
            let passes = n.div_ceil(Self::MAX_IMAGES_PER_PASS);
            let mut parts = Vec::with_capacity(passes);
            let mut start = 0;
            for p in 0..passes {
                let len = n / passes + usize::from(p < n % passes);
                parts.push(self.forward(&images.narrow(0, start, len)?)?);
                start += len;
            }
            return Ok(Tensor::cat(&parts, 0)?);
        }
        let normalized = self.normalize(images)?;
        let inputs = SCALE_FACTORS
            .iter()
            .map(|&s| {
                if s == 1.0 {
                    Ok(normalized.clone())
                } else {
                    self.resize(&normalized, s)
                }
            })
            .collect::<Result<Vec<_>>>()?;
        // The three scales' tokens share each linear layer's product.
        let scales = self.vit.forward_many(&inputs)?;
        let sum = scales[1..]
            .iter()
            .try_fold(scales[0].clone(), |acc, f| acc + f)?;
        Ok((sum / SCALE_FACTORS.len() as f64)?)
    }
}
