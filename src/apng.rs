//! Animated PNGs (APNG) written a frame at a time: a motion render's `animation.png` and a
//! turntable's, from linear RGB frames as 8-bit sRGB, so that a long clip at a large size never
//! sits in memory whole. Viewers without APNG show the first frame.

use crate::imageio::{io_error, linear_to_srgb8, ImageError, RgbImage};
use std::io::Write;
use std::path::{Path, PathBuf};

/// An animated PNG written a frame at a time, so that a long clip never sits in memory whole:
/// the number of frames and their size are fixed when it starts.
pub struct ApngStream<W: Write> {
    writer: png::Writer<W>,
    size: (usize, usize),
}

fn apng_error(e: impl std::fmt::Display) -> ImageError {
    ImageError::Decode("apng encoder".into(), e.to_string())
}

impl<W: Write> ApngStream<W> {
    /// Starts an APNG of `frames` frames of `size`, looping for ever, each shown `frame_ms`.
    pub fn new(w: W, size: (usize, usize), frames: usize, frame_ms: u16) -> Result<Self, ImageError> {
        let count = u32::try_from(frames).ok().filter(|&n| n > 0).ok_or_else(|| apng_error(format!("{frames} frames")))?;
        let mut encoder = png::Encoder::new(w, size.0 as u32, size.1 as u32);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        // Checked: finishing with fewer frames than announced is an error, not a short file.
        encoder.validate_sequence(true);
        encoder.set_animated(count, 0).map_err(apng_error)?;
        encoder.set_frame_delay(frame_ms, 1000).map_err(apng_error)?;
        let writer = encoder.write_header().map_err(apng_error)?;
        Ok(ApngStream { writer, size })
    }

    /// Appends the next frame (of the size the stream was started with).
    pub fn push(&mut self, frame: &RgbImage) -> Result<(), ImageError> {
        if (frame.width, frame.height) != self.size {
            return Err(apng_error("frames of different sizes"));
        }
        let raw: Vec<u8> = frame.pixels.iter().flat_map(|p| p.map(linear_to_srgb8)).collect();
        self.writer.write_image_data(&raw).map_err(apng_error)
    }

    /// Ends the stream; fails when fewer frames were pushed than it was started with.
    pub fn finish(self) -> Result<(), ImageError> {
        self.writer.finish().map_err(apng_error)
    }
}

/// An APNG streamed into a file of its own beside `path` and renamed onto `path` when it is
/// whole (`ApngStream`, atomically).
pub struct ApngFile {
    stream: ApngStream<std::fs::File>,
    temp: PathBuf,
    path: PathBuf,
}

impl ApngFile {
    pub fn create(path: &Path, size: (usize, usize), frames: usize, frame_ms: u16) -> Result<Self, ImageError> {
        let (temp, file) = crate::files::create_new_beside(path, "tmp").map_err(|e| io_error(path, e))?;
        match ApngStream::new(file, size, frames, frame_ms) {
            Ok(stream) => Ok(ApngFile { stream, temp, path: path.to_path_buf() }),
            Err(e) => {
                let _ = std::fs::remove_file(&temp);
                Err(e)
            }
        }
    }

    pub fn push(&mut self, frame: &RgbImage) -> Result<(), ImageError> {
        let pushed = self.stream.push(frame);
        if pushed.is_err() {
            let _ = std::fs::remove_file(&self.temp);
        }
        pushed
    }

    /// Ends the stream and moves the file into place.
    pub fn finish(self) -> Result<(), ImageError> {
        let ApngFile { stream, temp, path } = self;
        // The file is checked to end with its IEND chunk before it takes the name.
        let result = stream.finish().and_then(|_| ends_with_iend(&temp).map_err(|e| io_error(&path, e)));
        let result = result.and_then(|_| std::fs::rename(&temp, &path).map_err(|e| io_error(&path, e)));
        if result.is_err() {
            let _ = std::fs::remove_file(&temp);
        }
        result
    }
}

/// Syncs the PNG at `path` and checks that it ends with its IEND chunk (a whole file).
fn ends_with_iend(path: &Path) -> std::io::Result<()> {
    use std::io::{Read, Seek, SeekFrom};
    const IEND: [u8; 12] = [0, 0, 0, 0, b'I', b'E', b'N', b'D', 0xAE, 0x42, 0x60, 0x82];
    let mut file = std::fs::File::open(path)?;
    file.sync_all()?;
    let mut tail = [0u8; 12];
    file.seek(SeekFrom::End(-12))?;
    file.read_exact(&mut tail)?;
    match tail == IEND {
        true => Ok(()),
        false => Err(std::io::Error::other("the animated PNG was not written whole")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_streamed_read_back_as_an_animation_of_those_frames() {
        let frames: Vec<RgbImage> = (0..3)
            .map(|k| {
                let mut image = RgbImage::new(5, 4);
                image.pixels.iter_mut().enumerate().for_each(|(p, c)| *c = [p as f32 / 20.0, k as f32 / 3.0, 0.5]);
                image
            })
            .collect();
        let dir = std::env::temp_dir().join(format!("umbra-apng-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("animation.png");
        let mut file = ApngFile::create(&path, (5, 4), 3, 40).unwrap();
        for frame in &frames {
            file.push(frame).unwrap();
        }
        file.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().unwrap();
        assert_eq!(reader.info().animation_control().map(|a| (a.num_frames, a.num_plays)), Some((3, 0)));
        let mut buffer = vec![0u8; reader.output_buffer_size().unwrap()];
        for frame in &frames {
            reader.next_frame(&mut buffer).unwrap();
            let expected: Vec<u8> = frame.pixels.iter().flat_map(|p| p.map(linear_to_srgb8)).collect();
            assert_eq!(&buffer[..expected.len()], &expected[..]);
        }
        // A frame of another size, and fewer frames than promised, are refused.
        let mut short = ApngStream::new(Vec::new(), (5, 4), 2, 40).unwrap();
        assert!(short.push(&RgbImage::new(4, 4)).is_err());
        short.push(&frames[0]).unwrap();
        assert!(short.finish().is_err());
        // A file left short is not moved into place, and its temporary file goes.
        let cut = dir.join("cut.png");
        let mut file = ApngFile::create(&cut, (5, 4), 2, 40).unwrap();
        file.push(&frames[0]).unwrap();
        assert!(file.finish().is_err());
        assert!(!cut.exists());
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1, "only the whole animation is left");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
