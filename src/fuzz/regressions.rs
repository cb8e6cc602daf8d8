//! One test per real bug the fuzz runs found (issue #15 item 4), each with its minimised input as
//! bytes: the reader must refuse it with an error naming the file (and the line or field), without
//! a panic and without allocating for a count the file cannot hold.

use std::path::Path;

use super::alloc_guard;

/// Runs `parse` on `bytes` written as `file_name`; returns its error and the peak allocation of
/// this thread while it ran.
fn refuse<T, E: std::fmt::Display>(
    file_name: &str,
    bytes: &[u8],
    parse: impl FnOnce(&Path) -> Result<T, E>,
) -> (String, usize) {
    let dir = tempfile::tempdir_in(super::default_work_root()).unwrap();
    let path = dir.path().join(file_name);
    std::fs::write(&path, bytes).unwrap();
    alloc_guard::arm(usize::MAX);
    alloc_guard::track_this_thread();
    alloc_guard::reset_thread_counters();
    let result = parse(&path);
    let peak_bytes = alloc_guard::thread_figures().peak_bytes;
    let error = match result {
        Ok(_) => panic!("{file_name}: the broken input was accepted"),
        Err(error) => error.to_string(),
    };
    assert!(
        error.contains(&path.display().to_string()),
        "the error does not name the file: {error}"
    );
    (error, peak_bytes)
}

const MIB: usize = 1 << 20;

/// Found by `asgreg fuzz` (ply-binary, 300 inputs, seed 1, input 11): a 705-byte file whose face
/// count was mutated to 4294967295 made the reader reserve 192 MiB (capacities were capped at
/// 2^24 records, not at what the file holds). Now capacities are capped by what the data can
/// hold, and the reading stops where the data ends, naming the element and record.
#[test]
fn ply_face_count_beyond_the_data_is_refused_before_allocating() {
    let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
property float y\nproperty float z\nelement face 4294967295\n\
property list uchar int vertex_indices\nend_header\n"
        .to_vec();
    for value in [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0] {
        bytes.extend_from_slice(&value.to_le_bytes());
    }
    bytes.push(3);
    for index in [0i32, 1, 2] {
        bytes.extend_from_slice(&index.to_le_bytes());
    }
    let (error, peak_bytes) = refuse("mesh.ply", &bytes, crate::io::mesh_file::read_mesh);
    assert!(
        error.contains("element 'face' 1") && error.contains("truncated"),
        "{error}"
    );
    assert!(peak_bytes < MIB, "allocated {peak_bytes} bytes");
}

/// The same in ASCII: a vertex count of 10^12 in a file of a few lines.
#[test]
fn ply_ascii_vertex_count_of_ten_to_the_twelve_is_refused_before_allocating() {
    let bytes = b"ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty double x\n\
property double y\nproperty double z\nelement face 1\nproperty list uchar int vertex_indices\n\
end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
    let (error, peak_bytes) = refuse("mesh.ply", bytes, crate::io::mesh_file::read_mesh);
    assert!(error.contains("element 'vertex' 3: line 13"), "{error}");
    assert!(peak_bytes < MIB, "allocated {peak_bytes} bytes");
}

/// Found by `asgreg fuzz` (flo, 300 inputs, seed 1, input 5): a 775-byte `.flo` whose height was
/// mutated made the reader allocate 1153 MiB before finding the file short. Now the header's size
/// is checked against the file's first.
#[test]
fn flo_size_beyond_the_file_is_refused_before_allocating() {
    let mut bytes = 202_021.25f32.to_le_bytes().to_vec();
    bytes.extend_from_slice(&12i32.to_le_bytes());
    bytes.extend_from_slice(&16_000_000i32.to_le_bytes());
    bytes.extend_from_slice(&[0; 16]);
    let (error, peak_bytes) = refuse("flow.flo", &bytes, crate::io::flo::read_flo);
    assert!(
        error.contains("12 x 16000000") && error.contains("cut short"),
        "{error}"
    );
    assert!(peak_bytes < MIB, "allocated {peak_bytes} bytes");
}

/// Found by `asgreg fuzz` (priors-offset, 10^4 inputs, seed 1, input 9010; minimised to these 8
/// bytes): a zone whose last character is not ASCII panicked (`split_at` inside a character).
/// The same parser reads `asgreg priors --zone`.
#[test]
fn utm_zone_ending_in_a_multibyte_character_is_refused() {
    let bytes = b"zone \xef\xbf\xbd";
    let (error, _) = refuse("utm_offset.txt", bytes, |path| {
        crate::priors::utm::LocalFrame::parse_file(path, std::str::from_utf8(bytes).unwrap())
    });
    assert!(error.contains("line 1: zone"), "{error}");
    assert_eq!(crate::priors::utm::UtmZone::parse("15é"), None);
    assert_eq!(crate::priors::utm::UtmZone::parse("é"), None);
}

/// Found reading the loader while writing the image targets (the mutations stopped at the PNG
/// checksums until they were recomputed): a PNG whose header claims 20000 × 20000 pixels in a
/// file of 70 bytes. The decoder allocates the whole image before decoding it, and its default
/// limit (512 MiB) let such a header reserve 400 MB; the loader's limit now follows the file's
/// size. (This test fails on the code before the fix.)
#[test]
fn png_claiming_more_pixels_than_its_file_can_hold_is_refused_before_allocating() {
    let mut bytes = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        bytes.extend_from_slice(&(data.len() as u32).to_be_bytes());
        bytes.extend_from_slice(kind);
        bytes.extend_from_slice(data);
        bytes.extend_from_slice(&[0; 4]);
    };
    let mut header = Vec::new();
    header.extend_from_slice(&20_000u32.to_be_bytes());
    header.extend_from_slice(&20_000u32.to_be_bytes());
    header.extend_from_slice(&[8, 0, 0, 0, 0]);
    chunk(b"IHDR", &header);
    chunk(b"IDAT", &[0x78, 0x01, 0x01, 0x00, 0x00, 0xff, 0xff]);
    chunk(b"IEND", &[]);
    super::targets::fix_png_checksums(&mut bytes);
    let (error, peak_bytes) = refuse("photo.png", &bytes, crate::io::images::load_gray);
    assert!(error.contains("limit"), "{error}");
    assert!(peak_bytes < 20 * MIB, "allocated {peak_bytes} bytes");
}

/// Found by `asgreg fuzz` (image-jpeg, 10^5 inputs, seed 2, input 60503): the 16×16 seed JPEG
/// with its width mutated to 32528 (255 rows) and cut to 701 bytes. The decoder filled the
/// missing data with grey (0.8 s), the loader then made an RGB f32 copy (95 MiB), and only then
/// refused the file as truncated: 150 MiB at once for 701 bytes. Now the end is checked first,
/// JPEG's decoder limit follows what a JPEG of this size can hold, and RGB photos go to grey
/// without the f32 copy.
#[test]
fn jpeg_cut_short_with_a_huge_width_is_refused_before_decoding() {
    let bytes = include_bytes!("../../tests/data/fuzz/jpeg_cut_32528x255.jpg");
    let (error, peak_bytes) = refuse("photo.jpg", bytes, crate::io::images::load_gray);
    assert!(error.contains("truncated"), "{error}");
    assert!(peak_bytes < MIB, "allocated {peak_bytes} bytes");
}
