//! 8-bit luma images and timestamped frames.

/// A row-major 8-bit grey image without padding (`stride == width`).
#[derive(Clone, PartialEq, Eq, Default)]
pub struct LumaImage {
    width: usize,
    height: usize,
    data: Vec<u8>,
}

impl std::fmt::Debug for LumaImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "LumaImage({}x{})", self.width, self.height)
    }
}

impl LumaImage {
    /// A black image.
    pub fn new(width: usize, height: usize) -> Self {
        Self { width, height, data: vec![0; width * height] }
    }

    /// Wraps `data` (row-major, `width * height` bytes); `None` when the length does not match.
    pub fn from_vec(width: usize, height: usize, data: Vec<u8>) -> Option<Self> {
        (data.len() == width * height).then_some(Self { width, height, data })
    }

    /// An image whose pixel (x, y) is `f(x, y)`.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> u8) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Self { width, height, data }
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    pub fn data(&self) -> &[u8] {
        &self.data
    }

    pub fn data_mut(&mut self) -> &mut [u8] {
        &mut self.data
    }

    pub fn into_vec(self) -> Vec<u8> {
        self.data
    }

    /// Pixel row `y`.
    pub fn row(&self, y: usize) -> &[u8] {
        &self.data[y * self.width..(y + 1) * self.width]
    }

    /// Pixel (x, y); panics when out of bounds, like slice indexing.
    pub fn get(&self, x: usize, y: usize) -> u8 {
        self.data[y * self.width + x]
    }

    /// Resizes in place, reusing the allocation; contents are unspecified afterwards.
    pub fn resize(&mut self, width: usize, height: usize) {
        self.width = width;
        self.height = height;
        self.data.resize(width * height, 0);
    }
}

/// One camera frame: the image and when the sensor captured it.
#[derive(Clone, Debug, Default)]
pub struct Frame {
    /// Frame counter of the source, increasing by one per delivered frame.
    pub seq: u64,
    /// Capture time in nanoseconds on the monotonic control clock.
    pub t_ns: u64,
    pub image: LumaImage,
}
