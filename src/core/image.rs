//! One image type for every per-pixel array of the crate (grey photos, gradient and ASG images,
//! depth maps, normal maps, face indices, masks, flow planes), in the spirit of kornia-rs's
//! `Image`: an [`Image`] owns its pixels, an [`ImageView`] borrows them, and both check at
//! construction that the buffer holds exactly `width_px × height_px` values. No function then
//! receives a buffer whose length does not match its width × height, and a function that takes
//! two images compares sizes, not lengths.
//!
//! Conventions: row-major, top row first, pixel `(col, row)` at `data[row * width_px + col]`.
//! Zero-sized images (`0 × h`, `w × 0`) are allowed: they are what `Default` gives for buffers
//! that are sized later; functions that need pixels check for them and say so.
//!
//! What a value means (grey 0..1, metres, a face index, whether a pixel is valid) is the name of
//! the field or variable holding the image, not a type alias: `Image<f32>` is the same type
//! whether it holds a photo or a depth map.

/// An image whose size did not match its buffer, or two images that should have the same size.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ImageError {
    #[error(
        "a {width_px}x{height_px} image needs {expected} values (width x height), the buffer has {found}"
    )]
    DataLength {
        width_px: usize,
        height_px: usize,
        /// `width_px × height_px` (`usize::MAX` when that overflows).
        expected: usize,
        found: usize,
    },
    #[error(
        "{what} is {found_width_px}x{found_height_px} px, expected {expected_width_px}x{expected_height_px} px"
    )]
    SizeMismatch {
        what: &'static str,
        expected_width_px: usize,
        expected_height_px: usize,
        found_width_px: usize,
        found_height_px: usize,
    },
}

/// Checks that `len` values fill a `width_px × height_px` image.
fn check_length(width_px: usize, height_px: usize, len: usize) -> Result<(), ImageError> {
    match width_px.checked_mul(height_px) {
        Some(expected) if expected == len => Ok(()),
        expected => Err(ImageError::DataLength {
            width_px,
            height_px,
            expected: expected.unwrap_or(usize::MAX),
            found: len,
        }),
    }
}

/// An owned image: `width_px × height_px` values, row-major, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct Image<T> {
    width_px: usize,
    height_px: usize,
    data: Vec<T>,
}

/// An empty `0 × 0` image (a buffer to be sized by [`Image::resize`] or [`Image::reset`]).
impl<T> Default for Image<T> {
    fn default() -> Self {
        Self {
            width_px: 0,
            height_px: 0,
            data: Vec::new(),
        }
    }
}

impl<T> Image<T> {
    /// An image of `data`, which must hold exactly `width_px × height_px` values.
    pub fn new(width_px: usize, height_px: usize, data: Vec<T>) -> Result<Self, ImageError> {
        check_length(width_px, height_px, data.len())?;
        Ok(Self {
            width_px,
            height_px,
            data,
        })
    }

    /// An image whose pixels are `f(col, row)`.
    pub fn from_fn(
        width_px: usize,
        height_px: usize,
        mut f: impl FnMut(usize, usize) -> T,
    ) -> Self {
        let mut data = Vec::with_capacity(width_px * height_px);
        for row in 0..height_px {
            for col in 0..width_px {
                data.push(f(col, row));
            }
        }
        Self {
            width_px,
            height_px,
            data,
        }
    }

    pub fn width_px(&self) -> usize {
        self.width_px
    }

    pub fn height_px(&self) -> usize {
        self.height_px
    }

    /// `(width_px, height_px)`.
    pub fn size(&self) -> (usize, usize) {
        (self.width_px, self.height_px)
    }

    /// Number of pixels, `width_px × height_px`.
    pub fn pixel_count(&self) -> usize {
        self.data.len()
    }

    /// Whether the image has no pixels.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The pixels, row-major (`width_px × height_px` of them).
    pub fn data(&self) -> &[T] {
        &self.data
    }

    /// The pixels, row-major, to write in place (the size cannot change through this).
    pub fn data_mut(&mut self) -> &mut [T] {
        &mut self.data
    }

    /// The pixel buffer, row-major.
    pub fn into_data(self) -> Vec<T> {
        self.data
    }

    /// A borrowed view of the whole image.
    pub fn view(&self) -> ImageView<'_, T> {
        ImageView {
            width_px: self.width_px,
            height_px: self.height_px,
            data: &self.data,
        }
    }

    /// The pixel at `(col, row)`; `None` outside the image.
    pub fn get(&self, col: usize, row: usize) -> Option<&T> {
        self.view().get(col, row)
    }

    /// The pixel at `(col, row)` to write; `None` outside the image.
    pub fn get_mut(&mut self, col: usize, row: usize) -> Option<&mut T> {
        (col < self.width_px && row < self.height_px)
            .then(|| &mut self.data[row * self.width_px + col])
    }

    /// The pixels of row `row` (panics when `row >= height_px`).
    pub fn row(&self, row: usize) -> &[T] {
        &self.data[row * self.width_px..(row + 1) * self.width_px]
    }

    /// A new image of `f` applied to every pixel.
    pub fn map<U>(&self, f: impl FnMut(&T) -> U) -> Image<U> {
        Image {
            width_px: self.width_px,
            height_px: self.height_px,
            data: self.data.iter().map(f).collect(),
        }
    }

    /// Errs unless this image is `width_px × height_px`; `what` names it in the error.
    pub fn check_size(
        &self,
        what: &'static str,
        width_px: usize,
        height_px: usize,
    ) -> Result<(), ImageError> {
        self.view().check_size(what, width_px, height_px)
    }
}

impl<T: Clone> Image<T> {
    /// A `width_px × height_px` image with every pixel `value`.
    pub fn filled(width_px: usize, height_px: usize, value: T) -> Self {
        Self {
            width_px,
            height_px,
            data: vec![value; width_px * height_px],
        }
    }

    /// Sets the size, keeping the allocation (it grows only when the pixel count does). The
    /// buffer is resized as a `Vec` is: existing values stay where they are in memory, new ones
    /// are `fill`. For buffers whose every pixel is written next; see [`Image::reset`] otherwise.
    pub fn resize(&mut self, width_px: usize, height_px: usize, fill: T) {
        self.width_px = width_px;
        self.height_px = height_px;
        self.data.resize(width_px * height_px, fill);
    }

    /// Sets the size and every pixel to `value`, keeping the allocation.
    pub fn reset(&mut self, width_px: usize, height_px: usize, value: T) {
        self.width_px = width_px;
        self.height_px = height_px;
        self.data.clear();
        self.data.resize(width_px * height_px, value);
    }

    /// Sets every pixel to `value`.
    pub fn fill(&mut self, value: T) {
        self.data.fill(value);
    }
}

/// A borrowed image: `width_px × height_px` values, row-major, top row first.
#[derive(Debug, PartialEq)]
pub struct ImageView<'a, T> {
    width_px: usize,
    height_px: usize,
    data: &'a [T],
}

// Derived Clone and Copy would require `T: Copy`; a view is copyable whatever it borrows.
impl<T> Clone for ImageView<'_, T> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<T> Copy for ImageView<'_, T> {}

impl<'a, T> ImageView<'a, T> {
    /// A view of `data`, which must hold exactly `width_px × height_px` values.
    pub fn new(width_px: usize, height_px: usize, data: &'a [T]) -> Result<Self, ImageError> {
        check_length(width_px, height_px, data.len())?;
        Ok(Self {
            width_px,
            height_px,
            data,
        })
    }

    pub fn width_px(&self) -> usize {
        self.width_px
    }

    pub fn height_px(&self) -> usize {
        self.height_px
    }

    /// `(width_px, height_px)`.
    pub fn size(&self) -> (usize, usize) {
        (self.width_px, self.height_px)
    }

    /// Number of pixels, `width_px × height_px`.
    pub fn pixel_count(&self) -> usize {
        self.data.len()
    }

    /// Whether the image has no pixels.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The pixels, row-major (`width_px × height_px` of them), for as long as the borrow lasts.
    pub fn data(&self) -> &'a [T] {
        self.data
    }

    /// The pixel at `(col, row)`; `None` outside the image.
    pub fn get(&self, col: usize, row: usize) -> Option<&'a T> {
        (col < self.width_px && row < self.height_px).then(|| &self.data[row * self.width_px + col])
    }

    /// The pixels of row `row` (panics when `row >= height_px`).
    pub fn row(&self, row: usize) -> &'a [T] {
        &self.data[row * self.width_px..(row + 1) * self.width_px]
    }

    /// Errs unless this image is `width_px × height_px`; `what` names it in the error.
    pub fn check_size(
        &self,
        what: &'static str,
        width_px: usize,
        height_px: usize,
    ) -> Result<(), ImageError> {
        if (self.width_px, self.height_px) == (width_px, height_px) {
            Ok(())
        } else {
            Err(ImageError::SizeMismatch {
                what,
                expected_width_px: width_px,
                expected_height_px: height_px,
                found_width_px: self.width_px,
                found_height_px: self.height_px,
            })
        }
    }

    /// An owned copy.
    pub fn to_image(&self) -> Image<T>
    where
        T: Clone,
    {
        Image {
            width_px: self.width_px,
            height_px: self.height_px,
            data: self.data.to_vec(),
        }
    }
}

impl<'a, T> From<&'a Image<T>> for ImageView<'a, T> {
    fn from(image: &'a Image<T>) -> Self {
        image.view()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn construction_checks_the_length_and_names_both_numbers() {
        let image = Image::new(3, 2, vec![0u8, 1, 2, 3, 4, 5]).unwrap();
        assert_eq!(image.size(), (3, 2));
        assert_eq!(image.get(2, 1), Some(&5));
        assert_eq!(image.get(3, 0), None);
        assert_eq!(image.get(0, 2), None);
        assert_eq!(image.row(1), &[3, 4, 5]);
        let error = Image::new(3, 2, vec![0u8; 5]).unwrap_err();
        assert_eq!(
            error,
            ImageError::DataLength {
                width_px: 3,
                height_px: 2,
                expected: 6,
                found: 5
            }
        );
        let message = error.to_string();
        assert!(message.contains("3x2") && message.contains('6') && message.contains('5'));
        let error = ImageView::new(usize::MAX, 2, &[0u8; 4]).unwrap_err();
        assert!(matches!(
            error,
            ImageError::DataLength {
                expected: usize::MAX,
                found: 4,
                ..
            }
        ));
        assert!(ImageView::new(2, 2, &[0u8; 4]).is_ok());
        assert!(ImageView::new(2, 2, &[0u8; 3]).is_err());
    }

    #[test]
    fn zero_sized_images_are_allowed_and_empty() {
        let image: Image<f32> = Image::default();
        assert_eq!(image.size(), (0, 0));
        assert!(image.is_empty());
        assert!(Image::<f32>::new(0, 7, Vec::new()).is_ok());
        assert!(Image::new(0, 7, vec![1.0f32]).is_err());
        assert_eq!(image.view().get(0, 0), None);
    }

    #[test]
    fn resize_keeps_the_allocation_and_reset_fills() {
        let mut image = Image::filled(4, 4, 7u32);
        let pointer = image.data().as_ptr();
        image.resize(2, 3, 0);
        assert_eq!(image.size(), (2, 3));
        assert_eq!(image.data(), &[7; 6]);
        assert_eq!(image.data().as_ptr(), pointer);
        image.reset(3, 2, 1);
        assert_eq!(image.data(), &[1; 6]);
        assert_eq!(image.data().as_ptr(), pointer);
        image.resize(4, 2, 9);
        assert_eq!(image.data(), &[1, 1, 1, 1, 1, 1, 9, 9]);
        *image.get_mut(0, 1).unwrap() = 5;
        assert_eq!(image.get(0, 1), Some(&5));
        assert!(image.get_mut(4, 0).is_none());
    }

    #[test]
    fn views_borrow_compare_sizes_and_copy_out() {
        let image = Image::from_fn(3, 2, |col, row| (10 * row + col) as u16);
        assert_eq!(image.data(), &[0, 1, 2, 10, 11, 12]);
        let view = image.view();
        let copy = view;
        assert_eq!(copy.get(1, 1), Some(&11));
        assert_eq!(view.to_image(), image);
        assert_eq!(ImageView::from(&image), view);
        assert!(view.check_size("mask", 3, 2).is_ok());
        let error = view.check_size("mask", 2, 3).unwrap_err();
        assert_eq!(error.to_string(), "mask is 3x2 px, expected 2x3 px");
        assert_eq!(image.map(|v| *v as f32 * 0.5).get(2, 1), Some(&6.0));
        assert_eq!(image.into_data().len(), 6);
    }
}
