//! PLY meshes: a reader for what real exporters write, and a writer that keeps georeferencing.
//!
//! PLY is how photogrammetry tools hand over meshes (COLMAP, OpenMVS, Open3D, Blender, Meshlab),
//! and each one adds its own properties: colours, confidences, texture coordinates, per-face lists,
//! extra elements. The reader takes what registration needs — vertex `x y z` (read into f64),
//! `nx ny nz` when all three are present, and the face list `vertex_indices` (or `vertex_index`),
//! fan-triangulating polygons — and skips everything else by its declared type. It parses the whole
//! file from one byte buffer (a 180k-face mesh reads in milliseconds) and its errors name the file
//! and the header line, or the element, record index and property where the data went wrong.
//!
//! The writer stores world coordinates as `double`, so a mesh in UTM coordinates (5e6 m, where f32
//! keeps only half a metre) survives a round trip to well below a millimetre.

use std::fmt::Write as _;
use std::path::Path;

use glam::Vec3;
use nalgebra::Vector3;

use crate::core::mesh::Mesh;
use crate::io::mesh_file::MeshIoError;

/// How [`write_ply`] encodes the data after the header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlyEncoding {
    /// Human-readable; f64 values are written in their shortest form that reads back exactly.
    Ascii,
    /// Compact and fast to read; what most tools write.
    BinaryLittleEndian,
}

/// Reads a triangle mesh from a PLY file (`ascii`, `binary_little_endian` or `binary_big_endian`).
///
/// Polygons with more than three vertices are fan-triangulated; elements other than `vertex` and
/// `face` (edges, materials, cameras …) and all other properties are skipped. A file without faces
/// is an error ([`crate::core::mesh::MeshError::NoFaces`]): registration renders the mesh.
pub fn read_ply(path: &Path) -> Result<Mesh, MeshIoError> {
    let geometry = read_ply_geometry(path)?;
    Mesh::from_world_owned(
        geometry.positions_m,
        geometry.faces,
        geometry.vertex_normals,
    )
    .map_err(|source| MeshIoError::Mesh {
        path: path.to_path_buf(),
        source,
    })
}

/// Bytes read from the file at a time when streaming binary data.
const STREAM_BUFFER_BYTES: usize = 1 << 20;

/// Binary files are streamed through a 1 MiB buffer (a 10^7-triangle city mesh is ~250 MB on
/// disk: holding the file beside the mesh would double the peak memory); ASCII files are read
/// whole (they are small: nobody writes a city in ASCII).
fn read_ply_geometry(path: &Path) -> Result<PlyGeometry, MeshIoError> {
    use std::io::{Read as _, Seek as _};
    let read_error = |source| MeshIoError::Read {
        path: path.to_path_buf(),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(read_error)?;
    let file_bytes = file.metadata().map_err(read_error)?.len();
    let mut prefix = Vec::new();
    (&mut file)
        .take(1 << 20)
        .read_to_end(&mut prefix)
        .map_err(read_error)?;
    let header = parse_header(&prefix).map_err(|error| error.with_path(path))?;
    if header.format == DataFormat::Ascii {
        let bytes = std::fs::read(path).map_err(read_error)?;
        return parse_ply(&bytes).map_err(|error| error.with_path(path));
    }
    file.seek(std::io::SeekFrom::Start(header.data_offset as u64))
        .map_err(read_error)?;
    let data_bytes =
        usize::try_from(file_bytes.saturating_sub(header.data_offset as u64)).unwrap_or(usize::MAX);
    // Never a buffer larger than the data (a header claiming 10^9 faces over a few bytes must not
    // cost a MiB: fuzz::regressions).
    let reader =
        std::io::BufReader::with_capacity(STREAM_BUFFER_BYTES.min(data_bytes.max(4096)), file);
    let (plans, has_normals) = plan_elements(&header).map_err(|error| error.with_path(path))?;
    // A read error other than the file's end is the file's, not a truncation.
    let (geometry, io_error) = if header.format == DataFormat::BinaryBigEndian {
        let mut source = StreamSource::<_, true> {
            reader,
            io_error: None,
        };
        let geometry = read_records(&mut source, &plans, has_normals, header.format, data_bytes);
        (geometry, source.io_error)
    } else {
        let mut source = StreamSource::<_, false> {
            reader,
            io_error: None,
        };
        let geometry = read_records(&mut source, &plans, has_normals, header.format, data_bytes);
        (geometry, source.io_error)
    };
    if let Some(source) = io_error {
        return Err(read_error(source));
    }
    geometry.map_err(|error| error.with_path(path))
}

/// The vertex and face counts a PLY file declares, read from its header alone (the first MiB of
/// the file), to judge its size before loading it ([`crate::io::mesh_file::check_mesh_fits`]).
pub(crate) fn read_ply_counts(path: &Path) -> Result<(u64, u64), MeshIoError> {
    use std::io::Read as _;
    let read_error = |source| MeshIoError::Read {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(read_error)?;
    let mut prefix = Vec::new();
    file.take(1 << 20)
        .read_to_end(&mut prefix)
        .map_err(read_error)?;
    let header = parse_header(&prefix).map_err(|error| error.with_path(path))?;
    let count = |name: &str| {
        header
            .elements
            .iter()
            .find(|element| element.name == name)
            .map_or(0, |element| element.count as u64)
    };
    Ok((count("vertex"), count("face")))
}

/// Writes a mesh as PLY: world coordinates as `double x y z` (so georeferenced meshes keep their
/// precision), `float nx ny nz` when the mesh has vertex normals, and faces as
/// `list uchar int vertex_indices` (the most widely read index type).
pub fn write_ply(path: &Path, mesh: &Mesh, encoding: PlyEncoding) -> Result<(), MeshIoError> {
    if mesh.vertex_count() > i32::MAX as usize {
        return Err(MeshIoError::Unwritable {
            path: path.to_path_buf(),
            message: format!(
                "{} vertices is more than PLY 'int' vertex indices can address",
                mesh.vertex_count()
            ),
        });
    }
    let write_error = |source| MeshIoError::Write {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::create(path).map_err(write_error)?;
    let mut writer = std::io::BufWriter::new(file);
    write_ply_contents(&mut writer, mesh, encoding).map_err(write_error)?;
    writer
        .into_inner()
        .map_err(|error| write_error(error.into_error()))?;
    Ok(())
}

fn write_ply_contents(
    writer: &mut impl std::io::Write,
    mesh: &Mesh,
    encoding: PlyEncoding,
) -> std::io::Result<()> {
    let normals = mesh.vertex_normals();
    let format_name = match encoding {
        PlyEncoding::Ascii => "ascii",
        PlyEncoding::BinaryLittleEndian => "binary_little_endian",
    };
    let mut header = format!(
        "ply\nformat {format_name} 1.0\ncomment written by asgreg\nelement vertex {}\n\
         property double x\nproperty double y\nproperty double z\n",
        mesh.vertex_count()
    );
    if normals.is_some() {
        header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    // Writing to a String cannot fail.
    let _ = write!(
        header,
        "element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.face_count()
    );
    writer.write_all(header.as_bytes())?;

    for vertex_index in 0..mesh.vertex_count() {
        let position = mesh.world_position(vertex_index);
        let normal = normals.map(|normals| normals[vertex_index]);
        match encoding {
            PlyEncoding::Ascii => {
                write!(writer, "{} {} {}", position.x, position.y, position.z)?;
                if let Some(normal) = normal {
                    write!(writer, " {} {} {}", normal.x, normal.y, normal.z)?;
                }
                writer.write_all(b"\n")?;
            }
            PlyEncoding::BinaryLittleEndian => {
                for coordinate in [position.x, position.y, position.z] {
                    writer.write_all(&coordinate.to_le_bytes())?;
                }
                if let Some(normal) = normal {
                    for component in [normal.x, normal.y, normal.z] {
                        writer.write_all(&component.to_le_bytes())?;
                    }
                }
            }
        }
    }
    for face in mesh.faces() {
        // Indices fit in i32: write_ply checked the vertex count.
        let [a, b, c] = face.map(|vertex_index| vertex_index as i32);
        match encoding {
            PlyEncoding::Ascii => writeln!(writer, "3 {a} {b} {c}")?,
            PlyEncoding::BinaryLittleEndian => {
                writer.write_all(&[3])?;
                for vertex_index in [a, b, c] {
                    writer.write_all(&vertex_index.to_le_bytes())?;
                }
            }
        }
    }
    Ok(())
}

/// What a PLY file holds for registration, before it becomes a validated [`Mesh`].
struct PlyGeometry {
    positions_m: Vec<Vector3<f64>>,
    faces: Vec<[u32; 3]>,
    vertex_normals: Option<Vec<Vec3>>,
}

/// A parse error before the file's path is attached.
#[derive(Debug)]
enum PlyParseError {
    Header {
        line_number: usize,
        message: String,
    },
    Data {
        element: String,
        index: usize,
        message: String,
    },
}

impl PlyParseError {
    fn header(line_number: usize, message: impl Into<String>) -> Self {
        Self::Header {
            line_number,
            message: message.into(),
        }
    }

    fn with_path(self, path: &Path) -> MeshIoError {
        let path = path.to_path_buf();
        match self {
            Self::Header {
                line_number,
                message,
            } => MeshIoError::PlyHeader {
                path,
                line_number,
                message,
            },
            Self::Data {
                element,
                index,
                message,
            } => MeshIoError::PlyData {
                path,
                element,
                index,
                message,
            },
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum DataFormat {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

/// The PLY scalar types; each has two names (`uchar` = `uint8` …).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ScalarType {
    Int8,
    UInt8,
    Int16,
    UInt16,
    Int32,
    UInt32,
    Float32,
    Float64,
}

const PLY_TYPE_NAMES: &str = "char, uchar, short, ushort, int, uint, float, double \
                              (or int8, uint8, int16, uint16, int32, uint32, float32, float64)";

impl ScalarType {
    fn from_name(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::Int8,
            "uchar" | "uint8" => Self::UInt8,
            "short" | "int16" => Self::Int16,
            "ushort" | "uint16" => Self::UInt16,
            "int" | "int32" => Self::Int32,
            "uint" | "uint32" => Self::UInt32,
            "float" | "float32" => Self::Float32,
            "double" | "float64" => Self::Float64,
            _ => return None,
        })
    }

    fn size_bytes(self) -> usize {
        match self {
            Self::Int8 | Self::UInt8 => 1,
            Self::Int16 | Self::UInt16 => 2,
            Self::Int32 | Self::UInt32 | Self::Float32 => 4,
            Self::Float64 => 8,
        }
    }

    fn is_integer(self) -> bool {
        !matches!(self, Self::Float32 | Self::Float64)
    }

    fn name(self) -> &'static str {
        match self {
            Self::Int8 => "char",
            Self::UInt8 => "uchar",
            Self::Int16 => "short",
            Self::UInt16 => "ushort",
            Self::Int32 => "int",
            Self::UInt32 => "uint",
            Self::Float32 => "float",
            Self::Float64 => "double",
        }
    }

    /// Decodes one value from exactly `size_bytes()` bytes. Every PLY type is exact in f64.
    #[inline(always)]
    fn decode<const BIG_ENDIAN: bool>(self, bytes: &[u8]) -> f64 {
        macro_rules! decode_as {
            ($type:ty, $size:literal) => {{
                let mut array = [0u8; $size];
                array.copy_from_slice(&bytes[..$size]);
                f64::from(if BIG_ENDIAN {
                    <$type>::from_be_bytes(array)
                } else {
                    <$type>::from_le_bytes(array)
                })
            }};
        }
        match self {
            Self::Int8 => decode_as!(i8, 1),
            Self::UInt8 => decode_as!(u8, 1),
            Self::Int16 => decode_as!(i16, 2),
            Self::UInt16 => decode_as!(u16, 2),
            Self::Int32 => decode_as!(i32, 4),
            Self::UInt32 => decode_as!(u32, 4),
            Self::Float32 => decode_as!(f32, 4),
            Self::Float64 => decode_as!(f64, 8),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PropertyKind {
    Scalar(ScalarType),
    List {
        count_type: ScalarType,
        item_type: ScalarType,
    },
}

#[derive(Debug)]
struct PropertyDeclaration {
    name: String,
    kind: PropertyKind,
    line_number: usize,
}

#[derive(Debug)]
struct ElementDeclaration {
    name: String,
    count: usize,
    properties: Vec<PropertyDeclaration>,
    line_number: usize,
}

impl ElementDeclaration {
    fn property_names(&self) -> String {
        if self.properties.is_empty() {
            return "none".to_owned();
        }
        self.properties
            .iter()
            .map(|property| property.name.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

#[derive(Debug)]
struct PlyHeader {
    format: DataFormat,
    elements: Vec<ElementDeclaration>,
    /// Line number of `end_header`, for errors about the header as a whole.
    end_line_number: usize,
    /// Byte offset of the first data byte.
    data_offset: usize,
}

fn parse_header(bytes: &[u8]) -> Result<PlyHeader, PlyParseError> {
    if !(bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n")) {
        let first_line = bytes.split(|&byte| byte == b'\n').next().unwrap_or(bytes);
        let preview: String = first_line
            .iter()
            .take(40)
            .flat_map(|byte| byte.escape_ascii())
            .map(char::from)
            .collect();
        return Err(PlyParseError::header(
            1,
            format!("not a PLY file: the first line is \"{preview}\", not \"ply\""),
        ));
    }
    let mut format = None;
    let mut elements: Vec<ElementDeclaration> = Vec::new();
    let mut position = 0;
    let mut line_number = 0;
    loop {
        let Some(line_length) = bytes[position..].iter().position(|&byte| byte == b'\n') else {
            return Err(PlyParseError::header(
                line_number + 1,
                "the header ends without an 'end_header' line",
            ));
        };
        line_number += 1;
        let raw_line = &bytes[position..position + line_length];
        let raw_line = raw_line.strip_suffix(b"\r").unwrap_or(raw_line);
        position += line_length + 1;
        if line_number == 1 {
            continue; // "ply", checked above
        }
        let line = std::str::from_utf8(raw_line).map_err(|_| {
            PlyParseError::header(
                line_number,
                "the header line is not text (is the header cut short?)",
            )
        })?;
        let mut words = line.split_ascii_whitespace();
        let Some(keyword) = words.next() else {
            continue;
        };
        let words: Vec<&str> = words.collect();
        match keyword {
            "comment" | "obj_info" => {}
            "format" => format = Some(parse_format(&words, line_number)?),
            "element" => {
                let [name, count] = words[..] else {
                    return Err(PlyParseError::header(
                        line_number,
                        format!("expected 'element <name> <count>', found '{line}'"),
                    ));
                };
                let count = count.parse::<usize>().map_err(|_| {
                    PlyParseError::header(
                        line_number,
                        format!("the count of element '{name}' is '{count}', not a non-negative integer"),
                    )
                })?;
                elements.push(ElementDeclaration {
                    name: name.to_owned(),
                    count,
                    properties: Vec::new(),
                    line_number,
                });
            }
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(PlyParseError::header(
                        line_number,
                        "a property before any 'element' line",
                    ));
                };
                let property = parse_property(&words, line, line_number)?;
                element.properties.push(property);
            }
            "end_header" => {
                let Some(format) = format else {
                    return Err(PlyParseError::header(
                        line_number,
                        "the header has no 'format' line",
                    ));
                };
                return Ok(PlyHeader {
                    format,
                    elements,
                    end_line_number: line_number,
                    data_offset: position,
                });
            }
            _ => {
                return Err(PlyParseError::header(
                    line_number,
                    format!("unknown header keyword '{keyword}'"),
                ))
            }
        }
    }
}

fn parse_format(words: &[&str], line_number: usize) -> Result<DataFormat, PlyParseError> {
    let [format_name, version] = words[..] else {
        return Err(PlyParseError::header(
            line_number,
            "expected 'format <ascii|binary_little_endian|binary_big_endian> 1.0'",
        ));
    };
    let format = match format_name {
        "ascii" => DataFormat::Ascii,
        "binary_little_endian" => DataFormat::BinaryLittleEndian,
        "binary_big_endian" => DataFormat::BinaryBigEndian,
        _ => {
            return Err(PlyParseError::header(
                line_number,
                format!(
                    "unknown format '{format_name}' (supported: ascii, binary_little_endian, \
                     binary_big_endian)"
                ),
            ))
        }
    };
    if version != "1.0" && version != "1" {
        return Err(PlyParseError::header(
            line_number,
            format!("PLY version '{version}' is not supported (only 1.0)"),
        ));
    }
    Ok(format)
}

fn parse_property(
    words: &[&str],
    line: &str,
    line_number: usize,
) -> Result<PropertyDeclaration, PlyParseError> {
    let scalar_type = |type_name: &str| {
        ScalarType::from_name(type_name).ok_or_else(|| {
            PlyParseError::header(
                line_number,
                format!("'{type_name}' is not a PLY type (the types are {PLY_TYPE_NAMES})"),
            )
        })
    };
    let (kind, name) = match words[..] {
        ["list", count_type_name, item_type_name, name] => {
            let count_type = scalar_type(count_type_name)?;
            if !count_type.is_integer() {
                return Err(PlyParseError::header(
                    line_number,
                    format!(
                        "the count type of list property '{name}' is '{count_type_name}'; a list \
                         count must be an integer type"
                    ),
                ));
            }
            let item_type = scalar_type(item_type_name)?;
            (
                PropertyKind::List {
                    count_type,
                    item_type,
                },
                name,
            )
        }
        [type_name, name] if type_name != "list" => {
            (PropertyKind::Scalar(scalar_type(type_name)?), name)
        }
        _ => {
            return Err(PlyParseError::header(
                line_number,
                format!(
                    "expected 'property <type> <name>' or 'property list <count type> <item type> \
                     <name>', found '{line}'"
                ),
            ))
        }
    };
    Ok(PropertyDeclaration {
        name: name.to_owned(),
        kind,
        line_number,
    })
}

/// What to do with one property of one record.
#[derive(Clone, Copy, Debug)]
enum PropertyAction {
    Position {
        axis: usize,
        value_type: ScalarType,
    },
    Normal {
        axis: usize,
        value_type: ScalarType,
    },
    FaceIndices {
        count_type: ScalarType,
        index_type: ScalarType,
    },
    SkipScalar(ScalarType),
    SkipList {
        count_type: ScalarType,
        item_type: ScalarType,
    },
}

#[derive(Debug)]
struct ElementPlan<'a> {
    declaration: &'a ElementDeclaration,
    actions: Vec<PropertyAction>,
}

/// Decides, from the header alone, what to do with every property of every element.
fn plan_elements(header: &PlyHeader) -> Result<(Vec<ElementPlan<'_>>, bool), PlyParseError> {
    let mut plans = Vec::with_capacity(header.elements.len());
    let mut vertex_element_seen = false;
    let mut has_normals = false;
    let mut face_element_seen = false;
    for element in &header.elements {
        let skip_all = || {
            element
                .properties
                .iter()
                .map(|property| skip_action(property.kind))
                .collect()
        };
        let actions = match element.name.as_str() {
            "vertex" if !vertex_element_seen => {
                vertex_element_seen = true;
                let (actions, normals) = plan_vertex_element(element)?;
                has_normals = normals;
                actions
            }
            "face" if !face_element_seen => {
                face_element_seen = true;
                plan_face_element(element)?
            }
            "vertex" | "face" => {
                return Err(PlyParseError::header(
                    element.line_number,
                    format!("a second '{}' element", element.name),
                ))
            }
            _ => skip_all(),
        };
        plans.push(ElementPlan {
            declaration: element,
            actions,
        });
    }
    if !vertex_element_seen {
        return Err(PlyParseError::header(
            header.end_line_number,
            "the header declares no 'vertex' element",
        ));
    }
    Ok((plans, has_normals))
}

fn skip_action(kind: PropertyKind) -> PropertyAction {
    match kind {
        PropertyKind::Scalar(value_type) => PropertyAction::SkipScalar(value_type),
        PropertyKind::List {
            count_type,
            item_type,
        } => PropertyAction::SkipList {
            count_type,
            item_type,
        },
    }
}

/// Returns the actions and whether the vertices carry all three normal components.
fn plan_vertex_element(
    element: &ElementDeclaration,
) -> Result<(Vec<PropertyAction>, bool), PlyParseError> {
    const POSITION_NAMES: [&str; 3] = ["x", "y", "z"];
    const NORMAL_NAMES: [&str; 3] = ["nx", "ny", "nz"];
    let has_all = |names: [&str; 3]| {
        names.iter().all(|name| {
            element
                .properties
                .iter()
                .any(|property| property.name == *name)
        })
    };
    if let Some(missing) = POSITION_NAMES.iter().find(|name| {
        !element
            .properties
            .iter()
            .any(|property| property.name == **name)
    }) {
        return Err(PlyParseError::header(
            element.line_number,
            format!(
                "element 'vertex' has no property '{missing}' (its properties: {})",
                element.property_names()
            ),
        ));
    }
    let has_normals = has_all(NORMAL_NAMES);
    let mut position_taken = [false; 3];
    let mut normal_taken = [false; 3];
    let mut actions = Vec::with_capacity(element.properties.len());
    for property in &element.properties {
        let position_axis = POSITION_NAMES
            .iter()
            .position(|name| *name == property.name);
        let normal_axis = NORMAL_NAMES
            .iter()
            .position(|name| *name == property.name)
            .filter(|_| has_normals);
        let action = match (property.kind, position_axis, normal_axis) {
            (PropertyKind::List { .. }, Some(_), _) | (PropertyKind::List { .. }, _, Some(_)) => {
                return Err(PlyParseError::header(
                    property.line_number,
                    format!(
                        "property '{}' of element 'vertex' is a list; x, y, z, nx, ny, nz must be \
                         scalars",
                        property.name
                    ),
                ))
            }
            (PropertyKind::Scalar(value_type), Some(axis), _) if !position_taken[axis] => {
                position_taken[axis] = true;
                PropertyAction::Position { axis, value_type }
            }
            (PropertyKind::Scalar(value_type), _, Some(axis)) if !normal_taken[axis] => {
                normal_taken[axis] = true;
                PropertyAction::Normal { axis, value_type }
            }
            // Anything else, including a repeated x, is read past.
            (kind, _, _) => skip_action(kind),
        };
        actions.push(action);
    }
    Ok((actions, has_normals))
}

fn plan_face_element(element: &ElementDeclaration) -> Result<Vec<PropertyAction>, PlyParseError> {
    let is_index_list_name = |name: &str| name == "vertex_indices" || name == "vertex_index";
    let Some(index_property_position) = element
        .properties
        .iter()
        .position(|property| is_index_list_name(&property.name))
    else {
        return Err(PlyParseError::header(
            element.line_number,
            format!(
                "element 'face' has no 'vertex_indices' (or 'vertex_index') list property (its \
                 properties: {})",
                element.property_names()
            ),
        ));
    };
    let mut actions = Vec::with_capacity(element.properties.len());
    for (property_position, property) in element.properties.iter().enumerate() {
        if property_position != index_property_position {
            actions.push(skip_action(property.kind));
            continue;
        }
        match property.kind {
            PropertyKind::Scalar(value_type) => {
                return Err(PlyParseError::header(
                    property.line_number,
                    format!(
                        "property '{}' of element 'face' is a single {}, not a list of vertex \
                         indices",
                        property.name,
                        value_type.name()
                    ),
                ))
            }
            PropertyKind::List {
                count_type,
                item_type,
            } => {
                if !item_type.is_integer() {
                    return Err(PlyParseError::header(
                        property.line_number,
                        format!(
                            "the items of '{}' are {}; vertex indices must be an integer type",
                            property.name,
                            item_type.name()
                        ),
                    ));
                }
                actions.push(PropertyAction::FaceIndices {
                    count_type,
                    index_type: item_type,
                });
            }
        }
    }
    Ok(actions)
}

/// Why a value could not be read; the caller adds the element, record and property.
#[derive(Debug)]
enum ValueError {
    /// No data left at all.
    EndOfData,
    /// ASCII: the record's line has fewer values than the header declares.
    LineTooShort { line_number: usize },
    /// ASCII: the record's line has more values than the header declares.
    LineTooLong { line_number: usize, extra: String },
    /// ASCII: a token is not a number.
    NotANumber {
        line_number: usize,
        token: String,
        value_type: ScalarType,
    },
}

impl ValueError {
    fn describe(&self, format: DataFormat) -> String {
        match self {
            Self::EndOfData => match format {
                DataFormat::Ascii => "the file ends here (too few data lines)".to_owned(),
                _ => "the binary data ends here (the file is truncated)".to_owned(),
            },
            Self::LineTooShort { line_number } => {
                format!("line {line_number} has fewer values than the header declares")
            }
            Self::LineTooLong { line_number, extra } => format!(
                "line {line_number} has more values than the header declares (from '{extra}' on)"
            ),
            Self::NotANumber {
                line_number,
                token,
                value_type,
            } => format!(
                "line {line_number}: '{token}' is not a {} value",
                value_type.name()
            ),
        }
    }
}

/// Record-by-record access to the data section, ASCII or binary.
trait RecordSource {
    fn begin_record(&mut self) -> Result<(), ValueError>;
    fn read_value(&mut self, value_type: ScalarType) -> Result<f64, ValueError>;
    fn skip_values(&mut self, value_type: ScalarType, count: usize) -> Result<(), ValueError>;
    fn end_record(&mut self) -> Result<(), ValueError>;
}

struct BinarySource<'a, const BIG_ENDIAN: bool> {
    data: &'a [u8],
    position: usize,
}

impl<const BIG_ENDIAN: bool> RecordSource for BinarySource<'_, BIG_ENDIAN> {
    #[inline(always)]
    fn begin_record(&mut self) -> Result<(), ValueError> {
        Ok(())
    }

    #[inline(always)]
    fn read_value(&mut self, value_type: ScalarType) -> Result<f64, ValueError> {
        let end = self.position + value_type.size_bytes();
        let bytes = self
            .data
            .get(self.position..end)
            .ok_or(ValueError::EndOfData)?;
        self.position = end;
        Ok(value_type.decode::<BIG_ENDIAN>(bytes))
    }

    #[inline(always)]
    fn skip_values(&mut self, value_type: ScalarType, count: usize) -> Result<(), ValueError> {
        let end = value_type
            .size_bytes()
            .checked_mul(count)
            .and_then(|length| self.position.checked_add(length))
            .filter(|&end| end <= self.data.len())
            .ok_or(ValueError::EndOfData)?;
        self.position = end;
        Ok(())
    }

    #[inline(always)]
    fn end_record(&mut self) -> Result<(), ValueError> {
        Ok(())
    }
}

/// Binary data read from a stream (a buffered file), value by value.
struct StreamSource<R, const BIG_ENDIAN: bool> {
    reader: R,
    /// A read error other than the end of the file (reported as the data ending there, with it).
    io_error: Option<std::io::Error>,
}

impl<R: std::io::BufRead, const BIG_ENDIAN: bool> RecordSource for StreamSource<R, BIG_ENDIAN> {
    #[inline(always)]
    fn begin_record(&mut self) -> Result<(), ValueError> {
        Ok(())
    }

    #[inline(always)]
    fn read_value(&mut self, value_type: ScalarType) -> Result<f64, ValueError> {
        let mut bytes = [0u8; 8];
        let bytes = &mut bytes[..value_type.size_bytes()];
        match self.reader.read_exact(bytes) {
            Ok(()) => Ok(value_type.decode::<BIG_ENDIAN>(bytes)),
            Err(error) => {
                if error.kind() != std::io::ErrorKind::UnexpectedEof {
                    self.io_error = Some(error);
                }
                Err(ValueError::EndOfData)
            }
        }
    }

    fn skip_values(&mut self, value_type: ScalarType, count: usize) -> Result<(), ValueError> {
        let mut left = value_type
            .size_bytes()
            .checked_mul(count)
            .ok_or(ValueError::EndOfData)?;
        while left > 0 {
            let available = match self.reader.fill_buf() {
                Ok(buffer) => buffer.len(),
                Err(error) => {
                    self.io_error = Some(error);
                    return Err(ValueError::EndOfData);
                }
            };
            if available == 0 {
                return Err(ValueError::EndOfData);
            }
            let step = available.min(left);
            self.reader.consume(step);
            left -= step;
        }
        Ok(())
    }

    #[inline(always)]
    fn end_record(&mut self) -> Result<(), ValueError> {
        Ok(())
    }
}

/// ASCII data: one record per line (blank lines are passed over), values separated by whitespace.
struct AsciiSource<'a> {
    data: &'a [u8],
    /// Start of the next unread line.
    next_line_start: usize,
    /// Number of the next unread line in the file (the header's lines included).
    next_line_number: usize,
    current_line: &'a [u8],
    current_line_number: usize,
    /// Position in `current_line`.
    cursor: usize,
}

impl<'a> AsciiSource<'a> {
    fn new(data: &'a [u8], first_line_number: usize) -> Self {
        Self {
            data,
            next_line_start: 0,
            next_line_number: first_line_number,
            current_line: &[],
            current_line_number: 0,
            cursor: 0,
        }
    }

    fn next_token(&mut self) -> Option<&'a [u8]> {
        let line = self.current_line;
        let mut start = self.cursor;
        while start < line.len() && line[start].is_ascii_whitespace() {
            start += 1;
        }
        let mut end = start;
        while end < line.len() && !line[end].is_ascii_whitespace() {
            end += 1;
        }
        self.cursor = end;
        (end > start).then(|| &line[start..end])
    }
}

impl RecordSource for AsciiSource<'_> {
    fn begin_record(&mut self) -> Result<(), ValueError> {
        loop {
            if self.next_line_start >= self.data.len() {
                return Err(ValueError::EndOfData);
            }
            let rest = &self.data[self.next_line_start..];
            let line_length = rest
                .iter()
                .position(|&byte| byte == b'\n')
                .unwrap_or(rest.len());
            self.current_line = &rest[..line_length];
            self.current_line_number = self.next_line_number;
            self.cursor = 0;
            self.next_line_start += line_length + 1;
            self.next_line_number += 1;
            if self
                .current_line
                .iter()
                .any(|byte| !byte.is_ascii_whitespace())
            {
                return Ok(());
            }
        }
    }

    fn read_value(&mut self, value_type: ScalarType) -> Result<f64, ValueError> {
        let line_number = self.current_line_number;
        let token = self
            .next_token()
            .ok_or(ValueError::LineTooShort { line_number })?;
        std::str::from_utf8(token)
            .ok()
            .and_then(|text| text.parse::<f64>().ok())
            .ok_or_else(|| ValueError::NotANumber {
                line_number,
                token: String::from_utf8_lossy(token).into_owned(),
                value_type,
            })
    }

    fn skip_values(&mut self, _value_type: ScalarType, count: usize) -> Result<(), ValueError> {
        for _ in 0..count {
            self.next_token().ok_or(ValueError::LineTooShort {
                line_number: self.current_line_number,
            })?;
        }
        Ok(())
    }

    fn end_record(&mut self) -> Result<(), ValueError> {
        match self.next_token() {
            None => Ok(()),
            Some(extra) => Err(ValueError::LineTooLong {
                line_number: self.current_line_number,
                extra: String::from_utf8_lossy(extra).into_owned(),
            }),
        }
    }
}

fn parse_ply(bytes: &[u8]) -> Result<PlyGeometry, PlyParseError> {
    let header = parse_header(bytes)?;
    let (plans, has_normals) = plan_elements(&header)?;
    let data = &bytes[header.data_offset..];
    match header.format {
        DataFormat::Ascii => read_records(
            &mut AsciiSource::new(data, header.end_line_number + 1),
            &plans,
            has_normals,
            header.format,
            data.len(),
        ),
        DataFormat::BinaryLittleEndian => read_records(
            &mut BinarySource::<false> { data, position: 0 },
            &plans,
            has_normals,
            header.format,
            data.len(),
        ),
        DataFormat::BinaryBigEndian => read_records(
            &mut BinarySource::<true> { data, position: 0 },
            &plans,
            has_normals,
            header.format,
            data.len(),
        ),
    }
}

/// The most records of `element` that `data_bytes` can hold: every record takes at least the
/// bytes of its properties (binary: each scalar's size, each list's count; ASCII: a character and
/// a separator per value). Capacities are reserved up to this, never up to a count the header
/// merely claims: a 700-byte file claiming 4 billion faces must not reserve gigabytes (the
/// reading then stops at the end of the data, naming the element and record).
fn records_data_can_hold(
    element: &ElementDeclaration,
    format: DataFormat,
    data_bytes: usize,
) -> usize {
    let record_bytes: usize = element
        .properties
        .iter()
        .map(|property| match (format, property.kind) {
            (DataFormat::Ascii, _) => 2,
            (_, PropertyKind::Scalar(scalar)) => scalar.size_bytes(),
            (_, PropertyKind::List { count_type, .. }) => count_type.size_bytes(),
        })
        .sum();
    // The last ASCII value may end the file without its separator.
    (data_bytes + 1) / record_bytes.max(1)
}

/// A list length or vertex index read as f64 must be a non-negative integer (ASCII could say -1 or
/// 2.5; binary signed types can be negative).
fn to_non_negative_integer(value: f64, limit: u32) -> Option<u32> {
    (value >= 0.0 && value.fract() == 0.0 && value <= f64::from(limit)).then_some(value as u32)
}

fn read_records<S: RecordSource>(
    source: &mut S,
    plans: &[ElementPlan<'_>],
    has_normals: bool,
    format: DataFormat,
    data_bytes: usize,
) -> Result<PlyGeometry, PlyParseError> {
    // Capacities are capped so that a lying header cannot make us allocate terabytes: by what the
    // data can hold, and by 2^24 records.
    let capacity_cap = 1 << 24;
    let capacity_of = |name: &str| {
        plans
            .iter()
            .find(|plan| plan.declaration.name == name)
            .map_or(0, |plan| {
                plan.declaration.count.min(records_data_can_hold(
                    plan.declaration,
                    format,
                    data_bytes,
                ))
            })
    };
    let vertex_count = capacity_of("vertex");
    let face_count = capacity_of("face");
    let mut positions_m = Vec::with_capacity(vertex_count.min(capacity_cap));
    let mut vertex_normals = Vec::with_capacity(if has_normals {
        vertex_count.min(capacity_cap)
    } else {
        0
    });
    let mut faces = Vec::with_capacity(face_count.min(capacity_cap));
    let mut polygon: Vec<u32> = Vec::with_capacity(16);

    for plan in plans {
        let element = plan.declaration;
        if element.properties.is_empty() {
            continue; // records without properties occupy no data
        }
        let is_vertex_element = plan
            .actions
            .iter()
            .any(|action| matches!(action, PropertyAction::Position { .. }));
        for index in 0..element.count {
            let data_error = |property: Option<&str>, message: String| PlyParseError::Data {
                element: element.name.clone(),
                index,
                message: match property {
                    Some(property) => format!("property '{property}': {message}"),
                    None => message,
                },
            };
            source
                .begin_record()
                .map_err(|error| data_error(None, error.describe(format)))?;
            let mut position = [0.0f64; 3];
            let mut normal = [0.0f32; 3];
            for (action, property) in plan.actions.iter().zip(&element.properties) {
                let value_error =
                    |error: ValueError| data_error(Some(&property.name), error.describe(format));
                match *action {
                    PropertyAction::Position { axis, value_type } => {
                        position[axis] = source.read_value(value_type).map_err(value_error)?;
                    }
                    PropertyAction::Normal { axis, value_type } => {
                        normal[axis] = source.read_value(value_type).map_err(value_error)? as f32;
                    }
                    PropertyAction::SkipScalar(value_type) => {
                        source.skip_values(value_type, 1).map_err(value_error)?;
                    }
                    PropertyAction::SkipList {
                        count_type,
                        item_type,
                    } => {
                        let count = read_list_length(source, count_type, &property.name, format)
                            .map_err(|message| data_error(None, message))?;
                        source
                            .skip_values(item_type, count as usize)
                            .map_err(value_error)?;
                    }
                    PropertyAction::FaceIndices {
                        count_type,
                        index_type,
                    } => {
                        let count = read_list_length(source, count_type, &property.name, format)
                            .map_err(|message| data_error(None, message))?;
                        if count < 3 {
                            return Err(data_error(
                                Some(&property.name),
                                format!(
                                    "the face has {count} vertex indices; a face needs at least 3"
                                ),
                            ));
                        }
                        polygon.clear();
                        for _ in 0..count {
                            let value = source.read_value(index_type).map_err(value_error)?;
                            let vertex_index = to_non_negative_integer(value, u32::MAX)
                                .ok_or_else(|| {
                                    data_error(
                                        Some(&property.name),
                                        format!("vertex index {value} is not a valid index"),
                                    )
                                })?;
                            polygon.push(vertex_index);
                        }
                        // Fan triangulation keeps the polygon's winding.
                        for corner in 1..polygon.len() - 1 {
                            faces.push([polygon[0], polygon[corner], polygon[corner + 1]]);
                        }
                    }
                }
            }
            source
                .end_record()
                .map_err(|error| data_error(None, error.describe(format)))?;
            if is_vertex_element {
                positions_m.push(Vector3::from(position));
                if has_normals {
                    vertex_normals.push(Vec3::from_array(normal));
                }
            }
        }
    }
    Ok(PlyGeometry {
        positions_m,
        faces,
        vertex_normals: has_normals.then_some(vertex_normals),
    })
}

fn read_list_length<S: RecordSource>(
    source: &mut S,
    count_type: ScalarType,
    property_name: &str,
    format: DataFormat,
) -> Result<u32, String> {
    let value = source.read_value(count_type).map_err(|error| {
        format!(
            "property '{property_name}' (list length): {}",
            error.describe(format)
        )
    })?;
    to_non_negative_integer(value, u32::MAX).ok_or_else(|| {
        format!("property '{property_name}': list length {value} is not a non-negative integer")
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::mesh::MeshError;
    use std::path::PathBuf;

    /// A tetrahedron with outward counter-clockwise faces and unit normals pointing away from its
    /// centroid.
    const TETRA_POSITIONS: [[f64; 3]; 4] = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ];
    const TETRA_FACES: [[u32; 3]; 4] = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];

    fn tetra_normals() -> [[f32; 3]; 4] {
        TETRA_POSITIONS.map(|p| {
            let n = Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32) - Vec3::splat(0.25);
            n.normalize().to_array()
        })
    }

    /// Little-endian (or big-endian) binary data built value by value, as an exporter writes it.
    #[derive(Default)]
    struct Bytes {
        data: Vec<u8>,
        big_endian: bool,
    }

    impl Bytes {
        fn big_endian() -> Self {
            Self {
                data: Vec::new(),
                big_endian: true,
            }
        }
        fn raw(&mut self, little: &[u8]) -> &mut Self {
            if self.big_endian {
                self.data.extend(little.iter().rev());
            } else {
                self.data.extend_from_slice(little);
            }
            self
        }
        fn f32(&mut self, v: f32) -> &mut Self {
            self.raw(&v.to_le_bytes())
        }
        fn f64(&mut self, v: f64) -> &mut Self {
            self.raw(&v.to_le_bytes())
        }
        fn u8(&mut self, v: u8) -> &mut Self {
            self.raw(&[v])
        }
        fn i8(&mut self, v: i8) -> &mut Self {
            self.raw(&v.to_le_bytes())
        }
        fn i16(&mut self, v: i16) -> &mut Self {
            self.raw(&v.to_le_bytes())
        }
        fn u16(&mut self, v: u16) -> &mut Self {
            self.raw(&v.to_le_bytes())
        }
        fn i32(&mut self, v: i32) -> &mut Self {
            self.raw(&v.to_le_bytes())
        }
        fn u32(&mut self, v: u32) -> &mut Self {
            self.raw(&v.to_le_bytes())
        }
    }

    struct TempPly {
        _dir: tempfile::TempDir,
        path: PathBuf,
    }

    fn write_temp(name: &str, header: &str, body: &[u8]) -> TempPly {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(name);
        let mut contents = header.as_bytes().to_vec();
        contents.extend_from_slice(body);
        std::fs::write(&path, contents).unwrap();
        TempPly { _dir: dir, path }
    }

    fn read_error(name: &str, header: &str, body: &[u8]) -> (MeshIoError, String) {
        let file = write_temp(name, header, body);
        let error = read_ply(&file.path).unwrap_err();
        let message = error.to_string();
        assert!(
            message.starts_with(&file.path.display().to_string()),
            "the message must start with the path: {message}"
        );
        (error, message)
    }

    fn assert_tetrahedron(mesh: &Mesh, expect_normals: bool) {
        assert_eq!(mesh.vertex_count(), 4);
        assert_eq!(mesh.faces(), &TETRA_FACES);
        for (vertex_index, expected) in TETRA_POSITIONS.iter().enumerate() {
            let error = (mesh.world_position(vertex_index) - Vector3::from(*expected)).norm();
            assert!(error < 1e-6, "vertex {vertex_index} is off by {error}");
        }
        match (mesh.vertex_normals(), expect_normals) {
            (Some(normals), true) => {
                for (normal, expected) in normals.iter().zip(tetra_normals()) {
                    assert!((*normal - Vec3::from_array(expected)).length() < 1e-6);
                }
            }
            (None, false) => {}
            (normals, _) => panic!("normals: expected {expect_normals}, got {normals:?}"),
        }
    }

    const COLMAP_HEADER_BODY: &str = "element vertex 4
property float x
property float y
property float z
property float nx
property float ny
property float nz
property uchar red
property uchar green
property uchar blue
element face 4
property list uchar int vertex_index
end_header
";

    #[test]
    fn colmap_ascii() {
        let header = format!("ply\nformat ascii 1.0\n{COLMAP_HEADER_BODY}");
        let mut body = String::new();
        for (p, n) in TETRA_POSITIONS.iter().zip(tetra_normals()) {
            body += &format!(
                "{} {} {} {} {} {} 200 100 50\n",
                p[0], p[1], p[2], n[0], n[1], n[2]
            );
        }
        for f in TETRA_FACES {
            body += &format!("3 {} {} {}\n", f[0], f[1], f[2]);
        }
        let file = write_temp("colmap_ascii.ply", &header, body.as_bytes());
        assert_tetrahedron(&read_ply(&file.path).unwrap(), true);
    }

    #[test]
    fn colmap_binary() {
        let header = format!("ply\nformat binary_little_endian 1.0\n{COLMAP_HEADER_BODY}");
        let mut body = Bytes::default();
        for (p, n) in TETRA_POSITIONS.iter().zip(tetra_normals()) {
            for c in p {
                body.f32(*c as f32);
            }
            for c in n {
                body.f32(c);
            }
            body.u8(200).u8(100).u8(50);
        }
        for f in TETRA_FACES {
            body.u8(3);
            for v in f {
                body.i32(v as i32);
            }
        }
        let file = write_temp("colmap_binary.ply", &header, &body.data);
        assert_tetrahedron(&read_ply(&file.path).unwrap(), true);
    }

    #[test]
    fn openmvs_binary_with_texcoord_lists() {
        let header = "ply
format binary_little_endian 1.0
comment TextureFile scene_dense_mesh_texture.png
element vertex 4
property float x
property float y
property float z
element face 4
property list uchar uint32 vertex_indices
property list uchar float texcoord
end_header
";
        let mut body = Bytes::default();
        for p in TETRA_POSITIONS {
            for c in p {
                body.f32(c as f32);
            }
        }
        for f in TETRA_FACES {
            body.u8(3);
            for v in f {
                body.u32(v);
            }
            body.u8(6);
            for t in [0.1, 0.2, 0.3, 0.4, 0.5, 0.6] {
                body.f32(t);
            }
        }
        let file = write_temp("openmvs.ply", header, &body.data);
        assert_tetrahedron(&read_ply(&file.path).unwrap(), false);
    }

    #[test]
    fn open3d_binary_doubles() {
        let header = "ply
format binary_little_endian 1.0
comment Created by Open3D
element vertex 4
property double x
property double y
property double z
property double nx
property double ny
property double nz
property uchar red
property uchar green
property uchar blue
element face 4
property list uchar uint vertex_indices
end_header
";
        let mut body = Bytes::default();
        for (p, n) in TETRA_POSITIONS.iter().zip(tetra_normals()) {
            for c in p {
                body.f64(*c);
            }
            for c in n {
                body.f64(f64::from(c));
            }
            body.u8(1).u8(2).u8(3);
        }
        for f in TETRA_FACES {
            body.u8(3);
            for v in f {
                body.u32(v);
            }
        }
        let file = write_temp("open3d.ply", header, &body.data);
        assert_tetrahedron(&read_ply(&file.path).unwrap(), true);
    }

    #[test]
    fn blender_ascii_cube_quads_are_fan_triangulated() {
        let header = "ply
format ascii 1.0
comment Created by Blender 2.93.0 - www.blender.org, source file: 'cube.blend'
element vertex 8
property float x
property float y
property float z
property float nx
property float ny
property float nz
property float s
property float t
element face 6
property list uchar uint vertex_indices
end_header
";
        let mut body = String::new();
        let corners: Vec<[f32; 3]> = (0..8)
            .map(|i| {
                [
                    if i & 1 == 0 { -1.0 } else { 1.0 },
                    if i & 2 == 0 { -1.0 } else { 1.0 },
                    if i & 4 == 0 { -1.0 } else { 1.0 },
                ]
            })
            .collect();
        for c in &corners {
            let n = Vec3::from_array(*c).normalize();
            body += &format!(
                "{} {} {} {} {} {} 0.25 0.75\n",
                c[0], c[1], c[2], n.x, n.y, n.z
            );
        }
        let quads = [
            [0, 2, 3, 1],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 6, 7, 3],
            [0, 4, 6, 2],
            [1, 3, 7, 5],
        ];
        for q in quads {
            body += &format!("4 {} {} {} {}\n", q[0], q[1], q[2], q[3]);
        }
        let file = write_temp("blender.ply", header, body.as_bytes());
        let mesh = read_ply(&file.path).unwrap();
        assert_eq!(mesh.vertex_count(), 8);
        assert_eq!(mesh.face_count(), 12);
        assert_eq!(mesh.faces()[0], [0, 2, 3]);
        assert_eq!(mesh.faces()[1], [0, 3, 1]);
        for (vertex_index, c) in corners.iter().enumerate() {
            let expected = Vector3::new(f64::from(c[0]), f64::from(c[1]), f64::from(c[2]));
            assert!((mesh.world_position(vertex_index) - expected).norm() < 1e-6);
            let normal = mesh.vertex_normals().unwrap()[vertex_index];
            assert!((normal - Vec3::from_array(*c).normalize()).length() < 1e-6);
        }
        // Every face of the closed cube points outward: its normal agrees with its centroid.
        for face_index in 0..mesh.face_count() {
            let centroid: Vec3 = mesh.faces()[face_index]
                .iter()
                .map(|&v| mesh.positions_local_m()[v as usize])
                .sum::<Vec3>()
                / 3.0;
            assert!(mesh.face_normal(face_index).dot(centroid) > 0.0);
        }
    }

    #[test]
    fn big_endian_pentagon_and_signed_types() {
        let header = "ply
format binary_big_endian 1.0
element vertex 5
property short x
property short y
property char z
element face 1
property list ushort short vertex_indices
end_header
";
        let mut body = Bytes::big_endian();
        let points = [(0i16, 0i16), (2, 0), (3, 2), (1, 3), (-1, 2)];
        for (x, y) in points {
            body.i16(x).i16(y).i8(-7);
        }
        body.u16(5);
        for v in 0..5 {
            body.i16(v);
        }
        let file = write_temp("big_endian.ply", header, &body.data);
        let mesh = read_ply(&file.path).unwrap();
        assert_eq!(mesh.faces(), &[[0, 1, 2], [0, 2, 3], [0, 3, 4]]);
        for (vertex_index, (x, y)) in points.iter().enumerate() {
            let expected = Vector3::new(f64::from(*x), f64::from(*y), -7.0);
            assert!((mesh.world_position(vertex_index) - expected).norm() < 1e-6);
        }
    }

    /// Every PLY type name, as a skipped scalar and as a skipped list, in front of and between the
    /// properties that matter, plus extra elements before, between and after vertices and faces.
    fn everything_to_skip_header(format: &str) -> String {
        let type_names = [
            "char", "uchar", "short", "ushort", "int", "uint", "float", "double", "int8", "uint8",
            "int16", "uint16", "int32", "uint32", "float32", "float64",
        ];
        let mut header = format!(
            "ply\nformat {format} 1.0\ncomment made up to cover every type\nobj_info generated \
             by a test\nelement material 2\nproperty uchar ambient_red\nproperty float \
             ambient_coeff\nelement vertex 4\n"
        );
        for name in type_names {
            header += &format!("property {name} before_{name}\n");
        }
        header += "property list uint8 int16 neighbours\nproperty float x\nproperty float y\n\
                   property double z\nproperty float quality\n\
                   element camera 1\nproperty list int uint8 name\nproperty float view_px\n\
                   element face 4\nproperty uchar red\nproperty list uint16 uint vertex_indices\n\
                   property list uchar float texcoord\nproperty int flags\n\
                   element edge 2\nproperty int vertex1\nproperty int vertex2\nend_header\n";
        header
    }

    #[test]
    fn everything_else_is_skipped_in_binary() {
        let header = everything_to_skip_header("binary_little_endian");
        let mut body = Bytes::default();
        body.u8(10).f32(0.5).u8(20).f32(0.7); // materials
        for p in TETRA_POSITIONS {
            for _ in 0..2 {
                body.i8(-1)
                    .u8(255)
                    .i16(-2)
                    .u16(65535)
                    .i32(-3)
                    .u32(7)
                    .f32(1.5)
                    .f64(2.5);
            }
            body.u8(2).i16(1).i16(2); // neighbours list
            body.f32(p[0] as f32).f32(p[1] as f32).f64(p[2]).f32(0.9);
        }
        body.i32(3).u8(b'c').u8(b'a').u8(b'm').f32(600.0); // camera
        for f in TETRA_FACES {
            body.u8(9).u16(3).u32(f[0]).u32(f[1]).u32(f[2]);
            body.u8(6);
            for _ in 0..6 {
                body.f32(0.5);
            }
            body.i32(-1);
        }
        body.i32(0).i32(1).i32(1).i32(2); // edges
        let file = write_temp("skip.ply", &header, &body.data);
        assert_tetrahedron(&read_ply(&file.path).unwrap(), false);
    }

    #[test]
    fn everything_else_is_skipped_in_ascii() {
        let header = everything_to_skip_header("ascii");
        let mut body = String::from("10 0.5\n20 0.7\n");
        for p in TETRA_POSITIONS {
            body += "-1 255 -2 65535 -3 7 1.5 2.5 -1 255 -2 65535 -3 7 1.5 2.5 ";
            body += &format!("2 1 2 {} {} {} 0.9\n", p[0], p[1], p[2]);
        }
        body += "3 99 97 109 600\n\n"; // a blank line is passed over
        for f in TETRA_FACES {
            body += &format!("9 3 {} {} {} 6 0 0 1 0 1 1 -1\n", f[0], f[1], f[2]);
        }
        body += "0 1\n1 2\n";
        let file = write_temp("skip.ply", &header, body.as_bytes());
        assert_tetrahedron(&read_ply(&file.path).unwrap(), false);
    }

    #[test]
    fn crlf_header_and_partial_normals() {
        // Only nx and ny: not normals, just two more properties to skip.
        let header = "ply\r\nformat ascii 1.0\r\nelement vertex 4\r\nproperty float x\r\n\
                      property float y\r\nproperty float z\r\nproperty float nx\r\n\
                      property float ny\r\nelement face 4\r\n\
                      property list uchar int vertex_indices\r\nend_header\r\n";
        let mut body = String::new();
        for p in TETRA_POSITIONS {
            body += &format!("{} {} {} 0 1\r\n", p[0], p[1], p[2]);
        }
        for f in TETRA_FACES {
            body += &format!("3 {} {} {}\r\n", f[0], f[1], f[2]);
        }
        let file = write_temp("crlf.ply", header, body.as_bytes());
        assert_tetrahedron(&read_ply(&file.path).unwrap(), false);
    }

    fn georeferenced_tetrahedron() -> Mesh {
        let utm = Vector3::new(512_345.0, 5_401_234.0, 250.0);
        let positions: Vec<Vector3<f64>> = TETRA_POSITIONS
            .iter()
            .map(|p| utm + Vector3::new(p[0] * 3.217, p[1] * 2.5, p[2] * 0.731))
            .collect();
        let normals = tetra_normals().map(Vec3::from_array).to_vec();
        Mesh::from_world(&positions, TETRA_FACES.to_vec(), Some(normals)).unwrap()
    }

    #[test]
    fn round_trip_keeps_georeferenced_millimetres() {
        let original = georeferenced_tetrahedron();
        for encoding in [PlyEncoding::Ascii, PlyEncoding::BinaryLittleEndian] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("geo.ply");
            write_ply(&path, &original, encoding).unwrap();
            let read = read_ply(&path).unwrap();
            assert_eq!(read.faces(), original.faces(), "{encoding:?}");
            assert_eq!(read.vertex_count(), original.vertex_count());
            for vertex_index in 0..original.vertex_count() {
                let error = (read.world_position(vertex_index)
                    - original.world_position(vertex_index))
                .norm();
                assert!(
                    error < 1e-3,
                    "{encoding:?}: vertex {vertex_index} off by {error} m"
                );
            }
            assert_eq!(
                read.vertex_normals(),
                original.vertex_normals(),
                "{encoding:?}"
            );

            let mut without_normals = original.clone();
            without_normals.clear_vertex_normals();
            write_ply(&path, &without_normals, encoding).unwrap();
            assert_eq!(read_ply(&path).unwrap().vertex_normals(), None);
        }
    }

    #[test]
    fn written_header_is_what_other_tools_expect() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("geo.ply");
        write_ply(
            &path,
            &georeferenced_tetrahedron(),
            PlyEncoding::BinaryLittleEndian,
        )
        .unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let header_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let header = std::str::from_utf8(&bytes[..header_end]).unwrap();
        assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"));
        assert!(header.contains("property double x\nproperty double y\nproperty double z\n"));
        assert!(header.contains("property float nx\nproperty float ny\nproperty float nz\n"));
        assert!(header.contains("element face 4\nproperty list uchar int vertex_indices\n"));
        assert_eq!(bytes.len() - header_end, 4 * (24 + 12) + 4 * 13);
    }

    #[test]
    fn write_to_a_missing_directory_names_the_file() {
        let path = Path::new("/nonexistent/dir/out.ply");
        let error = write_ply(path, &georeferenced_tetrahedron(), PlyEncoding::Ascii).unwrap_err();
        assert!(matches!(error, MeshIoError::Write { .. }));
        assert!(error
            .to_string()
            .starts_with("/nonexistent/dir/out.ply: could not write"));
    }

    /// A patch of the Brighton Beach mesh with the original's header layout (binary, float32 x y z,
    /// uint8/uint32 face lists), cut as `tests/data/brighton_beach/README.md` says.
    #[test]
    fn brighton_beach_mesh_excerpt_reads() {
        let path = crate::test_data::repo_data("brighton_beach/mesh_excerpt.ply");
        let mesh = read_ply(&path).unwrap();
        assert_eq!(mesh.vertex_count(), 724);
        assert_eq!(mesh.face_count(), 1_335);
        assert!(mesh.vertex_normals().is_none());
        // A 6 m × 6 m patch of a flat park around (15.9, 63.2) near Z = 159.
        let (min, max) = mesh.bounds_world_m();
        assert!(
            (min.x - 12.92).abs() < 0.01 && (max.x - 18.91).abs() < 0.01,
            "{min} {max}"
        );
        assert!(
            (min.y - 60.18).abs() < 0.01 && (max.y - 66.17).abs() < 0.01,
            "{min} {max}"
        );
        assert!(min.z > 158.7 && max.z < 159.5, "{min} {max}");
    }

    #[test]
    #[ignore = "needs ../shared/data/brighton_beach (the shared data set beside the repo)"]
    fn shared_data_brighton_beach_mesh_reads_fast() {
        let path = crate::test_data::shared_data("brighton_beach/mesh.ply");
        let start = std::time::Instant::now();
        let mesh = read_ply(&path).unwrap();
        let elapsed = start.elapsed();
        println!(
            "read {} in {:.1} ms",
            path.display(),
            elapsed.as_secs_f64() * 1e3
        );
        assert_eq!(mesh.vertex_count(), 91_212);
        assert_eq!(mesh.face_count(), 182_135);
        assert!(mesh.vertex_normals().is_none());
        let (min, max) = mesh.bounds_world_m();
        assert!((max - min)
            .iter()
            .all(|extent| *extent > 1.0 && *extent < 10_000.0));
    }

    const TETRA_ASCII_BODY: &str =
        "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n";

    fn simple_header(vertex_properties: &str, face_properties: &str) -> String {
        format!(
            "ply\nformat ascii 1.0\nelement vertex 4\n{vertex_properties}element face 4\n\
             {face_properties}end_header\n"
        )
    }

    const XYZ: &str = "property float x\nproperty float y\nproperty float z\n";
    const INDICES: &str = "property list uchar int vertex_indices\n";

    #[test]
    fn the_simple_header_reads() {
        let file = write_temp(
            "ok.ply",
            &simple_header(XYZ, INDICES),
            TETRA_ASCII_BODY.as_bytes(),
        );
        assert_tetrahedron(&read_ply(&file.path).unwrap(), false);
    }

    #[test]
    fn missing_coordinate_is_named() {
        let header = simple_header("property float x\nproperty float z\n", INDICES);
        let (error, message) = read_error("no_y.ply", &header, b"");
        assert!(
            matches!(error, MeshIoError::PlyHeader { line_number: 3, .. }),
            "{error:?}"
        );
        assert!(message.contains("no property 'y'"), "{message}");
        assert!(message.contains("its properties: x, z"), "{message}");
    }

    #[test]
    fn coordinate_as_list_is_rejected() {
        let header = simple_header(
            "property list uchar float x\nproperty float y\nproperty float z\n",
            INDICES,
        );
        let (error, message) = read_error("list_x.ply", &header, b"");
        assert!(
            matches!(error, MeshIoError::PlyHeader { line_number: 4, .. }),
            "{error:?}"
        );
        assert!(
            message.contains("property 'x' of element 'vertex' is a list"),
            "{message}"
        );
    }

    #[test]
    fn face_without_index_list_is_rejected() {
        let header = simple_header(XYZ, "property list uchar int corners\nproperty uchar red\n");
        let (_, message) = read_error("no_indices.ply", &header, b"");
        assert!(message.contains("header line 7"), "{message}");
        assert!(
            message.contains("no 'vertex_indices' (or 'vertex_index')"),
            "{message}"
        );
        assert!(
            message.contains("its properties: corners, red"),
            "{message}"
        );

        let scalar = simple_header(XYZ, "property int vertex_indices\n");
        let (_, message) = read_error("scalar_indices.ply", &scalar, b"");
        assert!(
            message.contains("'vertex_indices' of element 'face' is a single int"),
            "{message}"
        );

        let float_items = simple_header(XYZ, "property list uchar float vertex_indices\n");
        let (_, message) = read_error("float_indices.ply", &float_items, b"");
        assert!(
            message.contains("items of 'vertex_indices' are float"),
            "{message}"
        );
    }

    #[test]
    fn float_list_count_is_rejected() {
        let header = simple_header(XYZ, "property list float int vertex_indices\n");
        let (error, message) = read_error("float_count.ply", &header, b"");
        assert!(
            matches!(error, MeshIoError::PlyHeader { line_number: 8, .. }),
            "{error:?}"
        );
        assert!(
            message.contains("count type of list property 'vertex_indices' is 'float'"),
            "{message}"
        );
    }

    #[test]
    fn unknown_format_is_rejected() {
        let header = "ply\nformat binary_middle_endian 1.0\nelement vertex 0\nend_header\n";
        let (error, message) = read_error("format.ply", header, b"");
        assert!(
            matches!(error, MeshIoError::PlyHeader { line_number: 2, .. }),
            "{error:?}"
        );
        assert!(
            message.contains("unknown format 'binary_middle_endian'"),
            "{message}"
        );
        assert!(message.contains("supported: ascii, binary_little_endian, binary_big_endian"));

        let version = "ply\nformat ascii 2.0\nend_header\n";
        let (_, message) = read_error("version.ply", version, b"");
        assert!(
            message.contains("version '2.0' is not supported"),
            "{message}"
        );

        let no_format = "ply\nelement vertex 0\nend_header\n";
        let (_, message) = read_error("no_format.ply", no_format, b"");
        assert!(
            message.contains("line 3: the header has no 'format' line"),
            "{message}"
        );
    }

    #[test]
    fn unknown_property_type_is_rejected() {
        let header = simple_header(
            "property real x\nproperty float y\nproperty float z\n",
            INDICES,
        );
        let (error, message) = read_error("type.ply", &header, b"");
        assert!(
            matches!(error, MeshIoError::PlyHeader { line_number: 4, .. }),
            "{error:?}"
        );
        assert!(message.contains("'real' is not a PLY type"), "{message}");

        let list_item = simple_header(XYZ, "property list uchar integer vertex_indices\n");
        let (_, message) = read_error("item_type.ply", &list_item, b"");
        assert!(message.contains("'integer' is not a PLY type"), "{message}");
    }

    #[test]
    fn malformed_header_lines_are_named() {
        let cases = [
            ("ply\nformat ascii 1.0\nproperty float x\nend_header\n", "line 3: a property before any 'element'"),
            ("ply\nformat ascii 1.0\nelement vertex many\nend_header\n", "line 3: the count of element 'vertex' is 'many'"),
            ("ply\nformat ascii 1.0\nelement vertex\nend_header\n", "line 3: expected 'element <name> <count>'"),
            ("ply\nformat ascii 1.0\nvertices 4\nend_header\n", "line 3: unknown header keyword 'vertices'"),
            ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float\nend_header\n", "line 4: expected 'property <type> <name>'"),
            ("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n", "line 5: the header ends without an 'end_header' line"),
            ("ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n", "line 5: the header declares no 'vertex' element"),
            ("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nelement vertex 0\nend_header\n", "line 7: a second 'vertex' element"),
        ];
        for (header, expected) in cases {
            let (error, message) = read_error("malformed.ply", header, b"");
            assert!(matches!(error, MeshIoError::PlyHeader { .. }), "{error:?}");
            assert!(
                message.contains(expected),
                "expected '{expected}' in: {message}"
            );
        }
    }

    #[test]
    fn garbage_is_not_a_ply_file() {
        let (error, message) = read_error("garbage.ply", "", b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR");
        assert!(
            matches!(error, MeshIoError::PlyHeader { line_number: 1, .. }),
            "{error:?}"
        );
        assert!(message.contains("not a PLY file"), "{message}");
        assert!(message.contains("\\x89PNG"), "{message}");

        let (_, message) = read_error("empty.ply", "", b"");
        assert!(message.contains("not a PLY file"), "{message}");

        let (_, message) = read_error("solid.ply", "solid cube\nfacet normal 0 0 1\n", b"");
        assert!(
            message.contains("the first line is \"solid cube\""),
            "{message}"
        );
    }

    #[test]
    fn truncated_binary_names_element_and_index() {
        let header = "ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\n\
                      property float y\nproperty float z\nelement face 4\n\
                      property list uchar int vertex_indices\nend_header\n";
        let mut body = Bytes::default();
        for p in TETRA_POSITIONS {
            for c in p {
                body.f32(c as f32);
            }
        }
        for f in TETRA_FACES {
            body.u8(3)
                .i32(f[0] as i32)
                .i32(f[1] as i32)
                .i32(f[2] as i32);
        }
        let complete = body.data.clone();
        let file = write_temp("complete.ply", header, &complete);
        assert_tetrahedron(&read_ply(&file.path).unwrap(), false);

        // Cut inside face 2's second index.
        let cut = &complete[..4 * 12 + 2 * 13 + 1 + 4 + 2];
        let (error, message) = read_error("cut_face.ply", header, cut);
        assert!(
            matches!(&error, MeshIoError::PlyData { element, index: 2, .. } if element == "face"),
            "{error:?}"
        );
        assert!(message.contains("element 'face' 2"), "{message}");
        assert!(message.contains("property 'vertex_indices'"), "{message}");
        assert!(message.contains("truncated"), "{message}");

        // Cut inside vertex 3's z.
        let (error, message) = read_error("cut_vertex.ply", header, &complete[..3 * 12 + 9]);
        assert!(
            matches!(&error, MeshIoError::PlyData { element, index: 3, .. } if element == "vertex"),
            "{error:?}"
        );
        assert!(message.contains("property 'z'"), "{message}");

        // Cut right before a face's list length.
        let (_, message) = read_error("cut_count.ply", header, &complete[..4 * 12 + 13]);
        assert!(message.contains("element 'face' 1"), "{message}");
        assert!(message.contains("(list length)"), "{message}");
    }

    #[test]
    fn too_few_ascii_lines_name_element_and_index() {
        let header = simple_header(XYZ, INDICES);
        let body = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n";
        let (error, message) = read_error("short.ply", &header, body.as_bytes());
        assert!(
            matches!(&error, MeshIoError::PlyData { element, index: 3, .. } if element == "face"),
            "{error:?}"
        );
        assert!(message.contains("too few data lines"), "{message}");

        let only_vertices = "0 0 0\n1 0 0\n";
        let (_, message) = read_error("shorter.ply", &header, only_vertices.as_bytes());
        assert!(message.contains("element 'vertex' 2"), "{message}");
    }

    #[test]
    fn bad_ascii_values_are_named_with_their_line() {
        let header = simple_header(XYZ, INDICES); // 9 header lines
        let short_line = "0 0 0\n1 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n";
        let (_, message) = read_error("short_line.ply", &header, short_line.as_bytes());
        assert!(
            message.contains("element 'vertex' 1: property 'z': line 11 has fewer values"),
            "{message}"
        );

        let long_line = "0 0 0\n1 0 0\n0 1 0 7\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n";
        let (_, message) = read_error("long_line.ply", &header, long_line.as_bytes());
        assert!(
            message.contains("element 'vertex' 2: line 12 has more values"),
            "{message}"
        );

        let not_a_number = "0 0 0\n1 zero 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n";
        let (_, message) = read_error("nan.ply", &header, not_a_number.as_bytes());
        assert!(
            message.contains("line 11: 'zero' is not a float value"),
            "{message}"
        );

        let negative_index = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 -1 3\n3 0 3 2\n3 1 2 3\n";
        let (_, message) = read_error("negative.ply", &header, negative_index.as_bytes());
        assert!(
            message.contains("element 'face' 1: property 'vertex_indices': vertex index -1"),
            "{message}"
        );

        let fractional_count = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3.5 0 1 3\n3 0 3 2\n3 1 2 3\n";
        let (_, message) = read_error("fraction.ply", &header, fractional_count.as_bytes());
        assert!(
            message.contains("element 'face' 1: property 'vertex_indices': list length 3.5"),
            "{message}"
        );

        let two_corners = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n2 0 1\n3 0 3 2\n3 1 2 3\n";
        let (_, message) = read_error("line_face.ply", &header, two_corners.as_bytes());
        assert!(
            message.contains("element 'face' 1: property 'vertex_indices': the face has 2"),
            "{message}"
        );
    }

    #[test]
    fn invalid_meshes_pass_the_mesh_error_through() {
        let header = simple_header(XYZ, INDICES);
        let out_of_range = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 4\n3 1 2 3\n";
        let (error, message) = read_error("range.ply", &header, out_of_range.as_bytes());
        assert!(
            matches!(
                error,
                MeshIoError::Mesh {
                    source: MeshError::IndexOutOfRange {
                        face_index: 2,
                        vertex_index: 4,
                        ..
                    },
                    ..
                }
            ),
            "{error:?}"
        );
        assert!(message.contains("face 2 refers to vertex 4"), "{message}");

        let point_cloud = format!("ply\nformat ascii 1.0\nelement vertex 4\n{XYZ}end_header\n");
        let (error, message) =
            read_error("cloud.ply", &point_cloud, b"0 0 0\n1 0 0\n0 1 0\n0 0 1\n");
        assert!(
            matches!(
                error,
                MeshIoError::Mesh {
                    source: MeshError::NoFaces,
                    ..
                }
            ),
            "{error:?}"
        );
        assert!(
            message.contains("cloud.ply: the mesh has no faces"),
            "{message}"
        );
    }

    #[test]
    fn missing_file_names_the_file() {
        let error = read_ply(Path::new("/nonexistent/mesh.ply")).unwrap_err();
        assert!(matches!(error, MeshIoError::Read { .. }));
        assert!(error
            .to_string()
            .starts_with("/nonexistent/mesh.ply: could not read the file"));
    }
}
