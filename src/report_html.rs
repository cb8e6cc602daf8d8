//! `OUT/report.html`: the one page a person opens after `register`, `eval` or `changes` to see at
//! a glance which photos registered and how well. It is self-contained (no network: CSS and
//! JavaScript inline, pictures as downscaled JPEG data URIs, plots as inline SVG), so it can be
//! mailed or archived with the results. Per frame: the verdict, the calibrated confidence, δ to
//! the ground truth where there is one, the timings, and the model over the photo before (prior)
//! and after (registered pose) with a slider between the two. The commands fill a [`ReportPage`];
//! this module only lays it out.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::core::image::{Image, ImageView};
use crate::core::undistort::resize_area;
use crate::io::images::{encode_rgb_jpeg, ImageIoError};

/// Width of the pictures embedded in the page, px (wider overlays are averaged down to it).
pub const THUMBNAIL_WIDTH_PX: usize = 480;
/// JPEG quality of the embedded pictures.
const THUMBNAIL_JPEG_QUALITY: u8 = 80;

/// Errors of writing the page; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("cannot encode a picture of frame {frame} for the report: {source}")]
    Picture {
        frame: String,
        #[source]
        source: ImageIoError,
    },
    #[error("cannot write the report {}: {source} (check that the output folder is writable)", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// What became of a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameVerdict {
    /// Registered and accepted by the calibrated confidence.
    Accepted,
    /// Registered, but the decision refused the pose.
    Rejected,
    /// No result: an input problem or an error (the reason says which).
    Failed,
    /// Processed without a verdict of its own (change detection).
    Done,
}

impl FrameVerdict {
    /// The word shown and the CSS class.
    pub fn name(self) -> &'static str {
        match self {
            FrameVerdict::Accepted => "accepted",
            FrameVerdict::Rejected => "rejected",
            FrameVerdict::Failed => "failed",
            FrameVerdict::Done => "done",
        }
    }
}

/// One embedded picture: a label ("before", "after", "changes") and the JPEG as a data URI.
#[derive(Clone, Debug)]
pub struct Picture {
    pub label: String,
    pub data_uri: String,
}

impl Picture {
    /// `image` averaged down to at most `max_width_px` wide (height in proportion) and embedded
    /// as a JPEG; `frame` names the frame in errors.
    pub fn from_rgb(
        frame: &str,
        label: &str,
        image: ImageView<'_, [u8; 3]>,
        max_width_px: usize,
    ) -> Result<Self, ReportError> {
        let small = downscale_rgb(image, max_width_px);
        let jpeg = encode_rgb_jpeg(small.view(), THUMBNAIL_JPEG_QUALITY).map_err(|source| {
            ReportError::Picture {
                frame: frame.to_string(),
                source,
            }
        })?;
        Ok(Self {
            label: label.to_string(),
            data_uri: format!("data:image/jpeg;base64,{}", base64(&jpeg)),
        })
    }
}

/// One row of the page.
#[derive(Clone, Debug)]
pub struct ReportFrame {
    pub name: String,
    /// What the frame belongs to, when a run has several (eval: level and method).
    pub group: Option<String>,
    pub verdict: FrameVerdict,
    /// Why the frame was not accepted, or a short note.
    pub reason: Option<String>,
    /// Calibrated confidence (0..1), when the method gives one.
    pub confidence: Option<f64>,
    /// δ of the prior to the ground truth, px, when there is a ground truth.
    pub initial_delta_px: Option<f64>,
    /// δ of the output pose to the ground truth, px, when there are both.
    pub delta_px: Option<f64>,
    /// Named times, milliseconds; a "total" entry is shown in the row, all in its details.
    pub timings_ms: Vec<(String, f64)>,
    /// Further facts shown in the row's details (support, counts, regions).
    pub details: Vec<(String, String)>,
    /// The first two are compared with a slider (before under, after over); more are shown after.
    pub pictures: Vec<Picture>,
}

/// The whole page.
#[derive(Clone, Debug, Default)]
pub struct ReportPage {
    /// The command that wrote it: "register", "eval", "changes".
    pub command: String,
    /// What it ran on (a folder, a scene).
    pub subject: String,
    /// Settings and totals shown at the top.
    pub summary: Vec<(String, String)>,
    /// Plots (caption, inline SVG document).
    pub plots_svg: Vec<(String, String)>,
    pub frames: Vec<ReportFrame>,
}

/// Writes `page` as one self-contained HTML file at `path`.
pub fn write_report_html(path: &Path, page: &ReportPage) -> Result<(), ReportError> {
    std::fs::write(path, render_report_html(page)).map_err(|source| ReportError::Write {
        path: path.to_path_buf(),
        source,
    })
}

const STYLE: &str = "body{font-family:system-ui,sans-serif;margin:1.5em;color:#222;background:#fff}
h1{font-size:1.4em}table{border-collapse:collapse}td,th{border-bottom:1px solid #ddd;padding:4px 8px;text-align:left;vertical-align:top}
th{background:#f3f3f3}.accepted .verdict{color:#1a7f37;font-weight:bold}.rejected .verdict{color:#b35900;font-weight:bold}
.failed .verdict{color:#c62828;font-weight:bold}.done .verdict{color:#1f5fa8;font-weight:bold}
.counts{font-size:1.2em;margin:.5em 0}.num{text-align:right;font-variant-numeric:tabular-nums}
.compare{position:relative;display:inline-block;line-height:0}.compare img{display:block;max-width:480px}
.compare img.over{position:absolute;left:0;top:0}.slider{width:100%;display:block}
.labels{display:flex;justify-content:space-between;font-size:.8em;color:#555}
.plots svg{max-width:100%;height:auto;border:1px solid #eee;margin:.5em 0}
.filters button{margin-right:.4em}.reason{color:#555;font-size:.9em;max-width:28em}details{font-size:.85em}";

const SCRIPT: &str = "(function(){
var rows=document.querySelectorAll('tr.frame');
document.getElementById('frame-count').textContent=rows.length;
document.getElementById('accepted-count').textContent=document.querySelectorAll('tr.frame.accepted').length;
document.querySelectorAll('.compare-box').forEach(function(box){
 var range=box.querySelector('input.slider'),over=box.querySelector('img.over');
 function show(){over.style.clipPath='inset(0 '+(100-range.value)+'% 0 0)';}
 range.addEventListener('input',show);show();});
document.querySelectorAll('.filters button').forEach(function(b){b.addEventListener('click',function(){
 var want=b.getAttribute('data-show');
 rows.forEach(function(r){r.style.display=(want==='all'||r.classList.contains(want))?'':'none';});});});
document.body.setAttribute('data-ready','1');
})();";

/// The page's HTML.
pub fn render_report_html(page: &ReportPage) -> String {
    let mut html = String::with_capacity(64 * 1024);
    let title = format!("asgreg {}: {}", page.command, page.subject);
    let _ = write!(
        html,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{}</title><style>{STYLE}</style></head>\n<body>\n<h1>{}</h1>\n",
        escape(&title),
        escape(&title)
    );
    let _ = writeln!(
        html,
        "<p class=\"counts\">Frames: <span id=\"frame-count\" data-written=\"{}\">?</span>, accepted: <span id=\"accepted-count\">?</span></p>",
        page.frames.len()
    );
    if !page.summary.is_empty() {
        html.push_str("<table class=\"summary\">\n");
        for (key, value) in &page.summary {
            let _ = writeln!(
                html,
                "<tr><th>{}</th><td>{}</td></tr>",
                escape(key),
                escape(value)
            );
        }
        html.push_str("</table>\n");
    }
    if !page.plots_svg.is_empty() {
        html.push_str("<section class=\"plots\"><h2>Plots</h2>\n");
        for (caption, svg) in &page.plots_svg {
            let _ = writeln!(
                html,
                "<figure>{svg}<figcaption>{}</figcaption></figure>",
                escape(caption)
            );
        }
        html.push_str("</section>\n");
    }
    html.push_str("<h2>Frames</h2>\n<p class=\"filters\">Show: <button data-show=\"all\">all</button><button data-show=\"accepted\">accepted</button><button data-show=\"rejected\">rejected</button><button data-show=\"failed\">failed</button></p>\n");
    let has_group = page.frames.iter().any(|f| f.group.is_some());
    html.push_str("<table id=\"frames\"><thead><tr><th>frame</th>");
    if has_group {
        html.push_str("<th>run</th>");
    }
    html.push_str("<th>verdict</th><th>confidence</th><th>δ prior (px)</th><th>δ result (px)</th><th>time (ms)</th><th>model over the photo</th></tr></thead>\n<tbody>\n");
    for frame in &page.frames {
        frame_row(&mut html, frame, has_group);
    }
    html.push_str("</tbody></table>\n");
    let _ = write!(html, "<script>{SCRIPT}</script>\n</body></html>\n");
    html
}

fn frame_row(html: &mut String, frame: &ReportFrame, has_group: bool) {
    let verdict = frame.verdict.name();
    let _ = write!(
        html,
        "<tr class=\"frame {verdict}\"><td>{}</td>",
        escape(&frame.name)
    );
    if has_group {
        let _ = write!(
            html,
            "<td>{}</td>",
            escape(frame.group.as_deref().unwrap_or(""))
        );
    }
    let _ = write!(html, "<td><span class=\"verdict\">{verdict}</span>");
    if let Some(reason) = &frame.reason {
        let _ = write!(html, "<div class=\"reason\">{}</div>", escape(reason));
    }
    html.push_str("</td>");
    let number = |value: Option<f64>, digits: usize| {
        value
            .filter(|v| v.is_finite())
            .map(|v| format!("{v:.digits$}"))
            .unwrap_or_else(|| "–".to_string())
    };
    let total_ms = frame
        .timings_ms
        .iter()
        .find(|(name, _)| name.starts_with("total"))
        .map(|(_, ms)| *ms);
    let _ = write!(
        html,
        "<td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}",
        number(frame.confidence, 2),
        number(frame.initial_delta_px, 2),
        number(frame.delta_px, 2),
        number(total_ms, 0)
    );
    if !frame.timings_ms.is_empty() || !frame.details.is_empty() {
        html.push_str("<details><summary>details</summary>");
        for (name, ms) in &frame.timings_ms {
            let _ = write!(html, "{}: {ms:.1} ms<br>", escape(name));
        }
        for (key, value) in &frame.details {
            let _ = write!(html, "{}: {}<br>", escape(key), escape(value));
        }
        html.push_str("</details>");
    }
    html.push_str("</td><td>");
    match frame.pictures.as_slice() {
        [] => html.push('–'),
        [only] => {
            let _ = write!(
                html,
                "<div class=\"compare\"><img src=\"{}\" alt=\"{}\"></div><div class=\"labels\"><span>{}</span></div>",
                only.data_uri,
                escape(&only.label),
                escape(&only.label)
            );
        }
        [under, over, rest @ ..] => {
            let _ = write!(
                html,
                "<div class=\"compare-box\"><div class=\"compare\"><img class=\"under\" src=\"{}\" alt=\"{}\"><img class=\"over\" src=\"{}\" alt=\"{}\"></div>\
<input class=\"slider\" type=\"range\" min=\"0\" max=\"100\" value=\"50\" aria-label=\"{} / {}\">\
<div class=\"labels\"><span>← {}</span><span>{} →</span></div></div>",
                under.data_uri,
                escape(&under.label),
                over.data_uri,
                escape(&over.label),
                escape(&over.label),
                escape(&under.label),
                escape(&over.label),
                escape(&under.label)
            );
            for picture in rest {
                let _ = write!(
                    html,
                    "<div class=\"compare\"><img src=\"{}\" alt=\"{}\"></div><div class=\"labels\"><span>{}</span></div>",
                    picture.data_uri,
                    escape(&picture.label),
                    escape(&picture.label)
                );
            }
        }
    }
    html.push_str("</td></tr>\n");
}

/// Text for HTML element content and attribute values.
fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// An RGB image averaged down to at most `max_width_px` wide (each channel as
/// [`resize_area`] does it); narrower images are kept as they are.
fn downscale_rgb(image: ImageView<'_, [u8; 3]>, max_width_px: usize) -> Image<[u8; 3]> {
    let (width_px, height_px) = image.size();
    if width_px <= max_width_px.max(1) {
        return image.to_image();
    }
    let target_width_px = max_width_px.max(1);
    let target_height_px =
        ((height_px as f64 * target_width_px as f64 / width_px as f64).round() as usize).max(1);
    let mut channels: Vec<Image<f32>> = Vec::with_capacity(3);
    for channel in 0..3 {
        let plane: Vec<f32> = image.data().iter().map(|p| f32::from(p[channel])).collect();
        let mut out = Image::default();
        if let Ok(view) = ImageView::new(width_px, height_px, &plane) {
            resize_area(view, target_width_px, target_height_px, &mut out);
        }
        channels.push(out);
    }
    Image::from_fn(target_width_px, target_height_px, |col, row| {
        std::array::from_fn(|channel| {
            let value = channels[channel].get(col, row).copied().unwrap_or(0.0);
            value.clamp(0.0, 255.0).round() as u8
        })
    })
}

/// Standard base64 (RFC 4648, with padding).
fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            chunk.get(1).copied().unwrap_or(0),
            chunk.get(2).copied().unwrap_or(0),
        ];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for (index, shift) in [18u32, 12, 6, 0].into_iter().enumerate() {
            if index <= chunk.len() {
                out.push(char::from(ALPHABET[((n >> shift) & 63) as usize]));
            } else {
                out.push('=');
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc_4648_vectors() {
        for (input, expected) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(input.as_bytes()), expected, "{input:?}");
        }
    }

    #[test]
    fn pictures_are_downscaled_jpegs_and_text_is_escaped() {
        let photo = Image::filled(1000, 500, [200u8, 100, 50]);
        let picture = Picture::from_rgb("a.jpg", "before", photo.view(), 100).unwrap();
        assert!(picture.data_uri.starts_with("data:image/jpeg;base64,/9j/"));
        assert_eq!(downscale_rgb(photo.view(), 100).size(), (100, 50));
        assert_eq!(
            downscale_rgb(photo.view(), 100).get(10, 10),
            Some(&[200, 100, 50])
        );
        let page = ReportPage {
            command: "register".into(),
            subject: "<photos> & co".into(),
            frames: vec![ReportFrame {
                name: "x\"<y>.jpg".into(),
                group: None,
                verdict: FrameVerdict::Rejected,
                reason: Some("a < b".into()),
                confidence: Some(0.5),
                initial_delta_px: None,
                delta_px: Some(1.234),
                timings_ms: vec![("total".into(), 12.0)],
                details: vec![],
                pictures: vec![picture.clone(), picture],
            }],
            ..ReportPage::default()
        };
        let html = render_report_html(&page);
        assert!(html.contains("&lt;photos&gt; &amp; co"));
        assert!(html.contains("x&quot;&lt;y&gt;.jpg") && html.contains("a &lt; b"));
        assert!(html.contains("class=\"frame rejected\"") && html.contains("1.23"));
        assert!(html.contains("data-written=\"1\"") && html.contains("input class=\"slider\""));
        assert!(
            !html.contains("http://") && !html.contains("https://"),
            "no network"
        );
    }
}
