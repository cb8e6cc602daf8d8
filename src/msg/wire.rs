//! The one encode and the one decode function of the bus (layout in `msg`'s module comment).

use std::borrow::Cow;

use bytemuck::Pod;
use serde::de::DeserializeOwned;
use serde::Serialize;

use super::types::*;
use super::SCHEMA_VERSION;
use crate::core::reprojection::GridSamples;

/// First bytes of every message.
pub const MAGIC: [u8; 4] = *b"ASGR";
/// Size of the fixed header, bytes.
pub const HEADER_BYTES: usize = 48;
/// Largest bincode body a receiver accepts (bodies are small; bulk data is in arrays).
const MAX_META_BYTES: usize = 1 << 20;
/// Most arrays any message kind has.
const MAX_ARRAYS: usize = 8;

#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error("cannot encode the {kind:?} body: {detail}")]
    Body { kind: MessageKind, detail: String },
}

/// Why received bytes are not a message this build understands. The receiver logs it and goes on.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DecodeError {
    #[error("message of {got} bytes is shorter than the {HEADER_BYTES}-byte header")]
    TooShort { got: usize },
    #[error("not an asgreg message (magic {found:02x?}, expected \"ASGR\")")]
    BadMagic { found: [u8; 4] },
    #[error("schema version {found} (frame {frame_id}) but this build speaks version {SCHEMA_VERSION}: run the same asgreg version on every host")]
    WrongVersion { found: u16, frame_id: u64 },
    #[error("unknown message kind {found} (frame {frame_id})")]
    UnknownKind { found: u16, frame_id: u64 },
    #[error("{kind:?} message for frame {frame_id}: {detail}")]
    Corrupt {
        kind: MessageKind,
        frame_id: u64,
        detail: String,
    },
}

/// A message ready to be written: its length is known before the transport lends a buffer.
pub struct Encoded<'m> {
    fixed: [u8; HEADER_BYTES],
    meta: Vec<u8>,
    arrays: Vec<&'m [u8]>,
}

impl Encoded<'_> {
    /// Total size in bytes.
    pub fn len(&self) -> usize {
        let mut offset = align8(HEADER_BYTES + self.meta.len()) + 8 * self.arrays.len();
        for array in &self.arrays {
            offset = align8(offset) + array.len();
        }
        align8(offset)
    }

    /// Never: every message has at least its header.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Writes the message into `out`, which must be exactly [`Encoded::len`] bytes.
    pub fn write_to(&self, out: &mut [u8]) {
        debug_assert_eq!(out.len(), self.len());
        out[..HEADER_BYTES].copy_from_slice(&self.fixed);
        let mut offset = HEADER_BYTES;
        out[offset..offset + self.meta.len()].copy_from_slice(&self.meta);
        offset += self.meta.len();
        let table = align8(offset);
        out[offset..table].fill(0);
        offset = table;
        for array in &self.arrays {
            out[offset..offset + 8].copy_from_slice(&(array.len() as u64).to_le_bytes());
            offset += 8;
        }
        for array in &self.arrays {
            let start = align8(offset);
            out[offset..start].fill(0);
            out[start..start + array.len()].copy_from_slice(array);
            offset = start + array.len();
        }
        out[offset..].fill(0);
    }

    /// The message as a new byte vector (for transports without loans, and tests).
    pub fn to_vec(&self) -> Vec<u8> {
        let mut out = vec![0u8; self.len()];
        self.write_to(&mut out);
        out
    }
}

fn align8(offset: usize) -> usize {
    offset.div_ceil(8) * 8
}

fn bincode_config() -> bincode::config::Configuration {
    bincode::config::standard()
}

fn meta_bytes<T: Serialize>(kind: MessageKind, meta: &T) -> Result<Vec<u8>, EncodeError> {
    bincode::serde::encode_to_vec(meta, bincode_config()).map_err(|error| EncodeError::Body {
        kind,
        detail: error.to_string(),
    })
}

/// Whether two message bodies are the same value on the wire (their bincode bodies are equal
/// byte for byte; unlike `==`, a NaN equals itself): a consumer tells a result sent again
/// (re-delivery, harmless) from a second, different result for the same frame (a fault).
pub fn same_body<T: Serialize>(a: &T, b: &T) -> bool {
    match (
        bincode::serde::encode_to_vec(a, bincode_config()),
        bincode::serde::encode_to_vec(b, bincode_config()),
    ) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

/// Encodes a message: the only encode function of the bus.
pub fn encode<'m>(message: &'m Envelope<'_>) -> Result<Encoded<'m>, EncodeError> {
    let kind = message.body.kind();
    let (meta, arrays): (Vec<u8>, Vec<&'m [u8]>) = match &message.body {
        Body::Frame(frame) => (
            meta_bytes(kind, &frame.info)?,
            vec![
                bytemuck::cast_slice(&frame.image),
                bytemuck::cast_slice(&frame.depth_m),
            ],
        ),
        Body::FlowJob(job) => (
            meta_bytes(kind, &job.meta)?,
            vec![
                bytemuck::cast_slice(&job.query),
                bytemuck::cast_slice(&job.asg),
                bytemuck::cast_slice(&job.depth_m),
                bytemuck::cast_slice(&job.face_index),
            ],
        ),
        Body::Correspondences(set) => (
            meta_bytes(kind, &set.meta)?,
            vec![
                bytemuck::cast_slice(&set.image_points_px),
                bytemuck::cast_slice(&set.world_points_m),
                bytemuck::cast_slice(&set.grid.face_index),
                bytemuck::cast_slice(&set.grid.depth_m),
            ],
        ),
        Body::Hypothesis(body) => (
            meta_bytes(kind, &body.meta)?,
            vec![
                bytemuck::cast_slice(&body.grid.face_index),
                bytemuck::cast_slice(&body.grid.depth_m),
            ],
        ),
        Body::FrameFailed(body) => (meta_bytes(kind, body)?, Vec::new()),
        Body::PoseResult(body) => (meta_bytes(kind, body)?, Vec::new()),
        Body::Credit(body) => (meta_bytes(kind, body)?, Vec::new()),
        Body::Metrics(body) => (meta_bytes(kind, body)?, Vec::new()),
        Body::StreamEnd(body) => (meta_bytes(kind, body)?, Vec::new()),
        Body::FrameQuery(body) => (
            meta_bytes(kind, &body.info)?,
            vec![
                bytemuck::cast_slice(&body.query),
                bytemuck::cast_slice(&body.depth_m),
                bytemuck::cast_slice(&body.photo),
            ],
        ),
        Body::ChangeJob(job) => (
            meta_bytes(kind, &job.meta)?,
            vec![
                bytemuck::cast_slice(&job.depth_m),
                bytemuck::cast_slice(&job.photo),
                bytemuck::cast_slice(&job.neighbour_photos),
            ],
        ),
        Body::ChangeResult(body) => (meta_bytes(kind, body)?, Vec::new()),
        Body::ChangeSet(body) => (meta_bytes(kind, body)?, Vec::new()),
        Body::ChangeSight(sight) => (
            meta_bytes(kind, &sight.meta)?,
            vec![
                bytemuck::cast_slice(&sight.photo_depth_m),
                bytemuck::cast_slice(&sight.model_depth_m),
            ],
        ),
        Body::PoseLender(lender) => (
            meta_bytes(kind, &lender.meta)?,
            vec![bytemuck::cast_slice(&lender.query)],
        ),
    };
    let header = &message.header;
    let mut fixed = [0u8; HEADER_BYTES];
    fixed[0..4].copy_from_slice(&MAGIC);
    fixed[4..6].copy_from_slice(&SCHEMA_VERSION.to_le_bytes());
    fixed[6..8].copy_from_slice(&(kind as u16).to_le_bytes());
    fixed[8..16].copy_from_slice(&header.frame_id.to_le_bytes());
    fixed[16..24].copy_from_slice(&header.sequence.to_le_bytes());
    fixed[24..32].copy_from_slice(&header.capture_time_ns.to_le_bytes());
    fixed[32..40].copy_from_slice(&header.sent_time_ns.to_le_bytes());
    fixed[40..44].copy_from_slice(&(meta.len() as u32).to_le_bytes());
    fixed[44..48].copy_from_slice(&(arrays.len() as u32).to_le_bytes());
    Ok(Encoded {
        fixed,
        meta,
        arrays,
    })
}

fn u16_at(bytes: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([bytes[at], bytes[at + 1]])
}

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    let mut value = [0u8; 8];
    value.copy_from_slice(&bytes[at..at + 8]);
    u64::from_le_bytes(value)
}

struct Reader<'a> {
    bytes: &'a [u8],
    kind: MessageKind,
    frame_id: u64,
    meta: &'a [u8],
    arrays: Vec<&'a [u8]>,
}

impl<'a> Reader<'a> {
    fn corrupt(&self, detail: impl Into<String>) -> DecodeError {
        DecodeError::Corrupt {
            kind: self.kind,
            frame_id: self.frame_id,
            detail: detail.into(),
        }
    }

    fn meta<T: DeserializeOwned>(&self) -> Result<T, DecodeError> {
        let (value, used) = bincode::serde::decode_from_slice::<T, _>(
            self.meta,
            bincode_config().with_limit::<MAX_META_BYTES>(),
        )
        .map_err(|error| self.corrupt(format!("body: {error}")))?;
        if used != self.meta.len() {
            return Err(self.corrupt(format!("body: {} trailing bytes", self.meta.len() - used)));
        }
        Ok(value)
    }

    fn expect_arrays(&self, count: usize) -> Result<(), DecodeError> {
        if self.arrays.len() != count {
            return Err(self.corrupt(format!("{} arrays, expected {count}", self.arrays.len())));
        }
        Ok(())
    }

    /// Array `index` as `T`s: borrowed when the bytes are aligned for `T`, copied otherwise.
    fn array<T: Pod>(
        &self,
        index: usize,
        name: &str,
        expected_len: Option<usize>,
    ) -> Result<Blob<'a, T>, DecodeError> {
        let bytes = self.arrays[index];
        let element = std::mem::size_of::<T>();
        if bytes.len() % element != 0 {
            return Err(self.corrupt(format!(
                "array '{name}' has {} bytes, not a multiple of {element}",
                bytes.len()
            )));
        }
        let len = bytes.len() / element;
        if let Some(expected) = expected_len {
            if len != expected {
                return Err(self.corrupt(format!(
                    "array '{name}' has {len} values, expected {expected}"
                )));
            }
        }
        Ok(match bytemuck::try_cast_slice::<u8, T>(bytes) {
            Ok(values) => Cow::Borrowed(values),
            Err(_) => Cow::Owned(bytemuck::pod_collect_to_vec(bytes)),
        })
    }

    /// Array `index`: empty, or an image of `len` values.
    fn optional_image(
        &self,
        index: usize,
        name: &str,
        len: usize,
    ) -> Result<Blob<'a, f32>, DecodeError> {
        let values = self.array(index, name, None)?;
        if !values.is_empty() && values.len() != len {
            return Err(self.corrupt(format!(
                "array '{name}' has {} values, expected 0 or {len}",
                values.len()
            )));
        }
        Ok(values)
    }

    /// Arrays `first` and `first + 1`: a coarse view's grid samples at `stride_px` (face index,
    /// depth), each of the grid's sample count for the frame's camera; both empty for stride 0.
    fn grid(
        &self,
        first: usize,
        info: &FrameInfo,
        stride_px: u32,
    ) -> Result<GridArrays<'a>, DecodeError> {
        let len = match stride_px {
            0 => 0,
            stride_px => {
                self.image_len(info)?;
                let (width_px, height_px) = info.image_size();
                GridSamples::sample_count(width_px, height_px, stride_px as usize)
            }
        };
        Ok(GridArrays {
            face_index: self.array(first, "grid_face_index", Some(len))?,
            depth_m: self.array(first + 1, "grid_depth_m", Some(len))?,
        })
    }

    fn image_len(&self, info: &FrameInfo) -> Result<usize, DecodeError> {
        self.camera_len(&info.name, &info.camera)
    }

    fn camera_len(
        &self,
        name: &str,
        camera: &crate::core::camera::Camera,
    ) -> Result<usize, DecodeError> {
        let len = camera.width_px as usize * camera.height_px as usize;
        if len == 0 {
            return Err(self.corrupt(format!(
                "camera of frame '{name}' is {}×{} px",
                camera.width_px, camera.height_px
            )));
        }
        Ok(len)
    }
}

/// Decodes a message: the only decode function of the bus. Checks the magic, the schema version,
/// the kind, every length and the body; bulk arrays are borrowed from `bytes` where aligned.
pub fn decode(bytes: &[u8]) -> Result<Envelope<'_>, DecodeError> {
    if bytes.len() < HEADER_BYTES {
        return Err(DecodeError::TooShort { got: bytes.len() });
    }
    let mut magic = [0u8; 4];
    magic.copy_from_slice(&bytes[0..4]);
    if magic != MAGIC {
        return Err(DecodeError::BadMagic { found: magic });
    }
    let frame_id = u64_at(bytes, 8);
    let version = u16_at(bytes, 4);
    if version != SCHEMA_VERSION {
        return Err(DecodeError::WrongVersion {
            found: version,
            frame_id,
        });
    }
    let kind_value = u16_at(bytes, 6);
    let kind = MessageKind::from_wire(kind_value).ok_or(DecodeError::UnknownKind {
        found: kind_value,
        frame_id,
    })?;
    let header = Header {
        frame_id,
        sequence: u64_at(bytes, 16),
        capture_time_ns: u64_at(bytes, 24),
        sent_time_ns: u64_at(bytes, 32),
    };
    let meta_len = u32_at(bytes, 40) as usize;
    let array_count = u32_at(bytes, 44) as usize;
    let mut reader = Reader {
        bytes,
        kind,
        frame_id,
        meta: &[],
        arrays: Vec::new(),
    };
    if meta_len > MAX_META_BYTES || HEADER_BYTES + meta_len > bytes.len() {
        return Err(reader.corrupt(format!(
            "body length {meta_len} does not fit in {} bytes",
            bytes.len()
        )));
    }
    if array_count > MAX_ARRAYS {
        return Err(reader.corrupt(format!("{array_count} arrays (at most {MAX_ARRAYS})")));
    }
    reader.meta = &bytes[HEADER_BYTES..HEADER_BYTES + meta_len];
    let mut offset = align8(HEADER_BYTES + meta_len);
    if offset + 8 * array_count > bytes.len() {
        return Err(reader.corrupt("array table runs past the end"));
    }
    let lengths: Vec<u64> = (0..array_count)
        .map(|i| u64_at(bytes, offset + 8 * i))
        .collect();
    offset += 8 * array_count;
    for (index, &len) in lengths.iter().enumerate() {
        let start = align8(offset);
        let end = usize::try_from(len)
            .ok()
            .and_then(|len| start.checked_add(len))
            .filter(|&end| end <= reader.bytes.len())
            .ok_or_else(|| {
                reader.corrupt(format!("array {index} ({len} bytes) runs past the end"))
            })?;
        reader.arrays.push(&reader.bytes[start..end]);
        offset = end;
    }
    let body = match kind {
        MessageKind::Frame => {
            reader.expect_arrays(2)?;
            let info: FrameInfo = reader.meta()?;
            let len = reader.image_len(&info)?;
            let image = reader.array(0, "image", Some(len))?;
            let depth_m = reader.optional_image(1, "depth_m", len)?;
            Body::Frame(Frame {
                info,
                image,
                depth_m,
            })
        }
        MessageKind::FlowJob => {
            reader.expect_arrays(4)?;
            let meta: FlowJobMeta = reader.meta()?;
            let len = reader.image_len(&meta.info)?;
            Body::FlowJob(FlowJob {
                query: reader.array(0, "query", Some(len))?,
                asg: reader.array(1, "asg", Some(len))?,
                depth_m: reader.array(2, "depth_m", Some(len))?,
                face_index: reader.array(3, "face_index", Some(len))?,
                meta,
            })
        }
        MessageKind::Correspondences => {
            reader.expect_arrays(4)?;
            let meta: CorrespondencesMeta = reader.meta()?;
            let world_points_m: Blob<f64> = reader.array(1, "world_points_m", None)?;
            let count = world_points_m.len() / 3;
            let grid = reader.grid(2, &meta.info, meta.grid_stride_px)?;
            Body::Correspondences(Correspondences {
                image_points_px: reader.array(0, "image_points_px", Some(2 * count))?,
                world_points_m: reader.array(1, "world_points_m", Some(3 * count))?,
                grid,
                meta,
            })
        }
        MessageKind::Hypothesis => {
            reader.expect_arrays(2)?;
            let meta: HypothesisMeta = reader.meta()?;
            let grid = reader.grid(0, &meta.info, meta.grid_stride_px)?;
            Body::Hypothesis(Hypothesis { meta, grid })
        }
        MessageKind::FrameFailed => {
            reader.expect_arrays(0)?;
            Body::FrameFailed(reader.meta()?)
        }
        MessageKind::PoseResult => {
            reader.expect_arrays(0)?;
            Body::PoseResult(reader.meta()?)
        }
        MessageKind::Credit => {
            reader.expect_arrays(0)?;
            Body::Credit(reader.meta()?)
        }
        MessageKind::Metrics => {
            reader.expect_arrays(0)?;
            Body::Metrics(reader.meta()?)
        }
        MessageKind::StreamEnd => {
            reader.expect_arrays(0)?;
            Body::StreamEnd(reader.meta()?)
        }
        MessageKind::FrameQuery => {
            reader.expect_arrays(3)?;
            let info: FrameInfo = reader.meta()?;
            let len = reader.image_len(&info)?;
            Body::FrameQuery(FrameQuery {
                query: reader.array(0, "query", Some(len))?,
                depth_m: reader.optional_image(1, "depth_m", len)?,
                photo: reader.optional_image(2, "photo", len)?,
                info,
            })
        }
        MessageKind::ChangeJob => {
            reader.expect_arrays(3)?;
            let meta: ChangeJobMeta = reader.meta()?;
            let len = reader.camera_len(&meta.info.name, &meta.camera)?;
            let mut neighbours_len = 0;
            for neighbour in &meta.neighbours {
                neighbours_len += reader.camera_len(&neighbour.name, &neighbour.camera)?;
            }
            Body::ChangeJob(ChangeJob {
                depth_m: reader.optional_image(0, "depth_m", len)?,
                photo: reader.optional_image(1, "photo", len)?,
                neighbour_photos: reader.array(2, "neighbour_photos", Some(neighbours_len))?,
                meta,
            })
        }
        MessageKind::ChangeResult => {
            reader.expect_arrays(0)?;
            Body::ChangeResult(reader.meta()?)
        }
        MessageKind::ChangeSet => {
            reader.expect_arrays(0)?;
            Body::ChangeSet(reader.meta()?)
        }
        MessageKind::ChangeSight => {
            reader.expect_arrays(2)?;
            let meta: ChangeSightMeta = reader.meta()?;
            // With a change map, both depths of the registered camera's size; without, none.
            let len = match &meta.view {
                Some(view) => reader.camera_len(&meta.result.name, &view.camera)?,
                None => 0,
            };
            Body::ChangeSight(ChangeSight {
                photo_depth_m: reader.array(0, "photo_depth_m", Some(len))?,
                model_depth_m: reader.array(1, "model_depth_m", Some(len))?,
                meta,
            })
        }
        MessageKind::PoseLender => {
            reader.expect_arrays(1)?;
            let meta: PoseLenderMeta = reader.meta()?;
            let len = reader.image_len(&meta.info)?;
            Body::PoseLender(PoseLender {
                query: reader.array(0, "query", Some(len))?,
                meta,
            })
        }
    };
    Ok(Envelope { header, body })
}
