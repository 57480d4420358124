//! A photograph's metadata and what a result keeps of it (pure layer): the keyframe's EXIF
//! (read and rewritten with `kamadak-exif`: orientation 1 since results are stored upright,
//! no thumbnail, clearview as the software, the pixel size of the result), its XMP (with a
//! description of clearview's own: which views filled the result, and where its report is),
//! its IPTC and its colour space.

use std::io::Cursor;

use exif::experimental::Writer;
use exif::{Field, In, Tag, Value};

use super::colour::Space;

/// What the EXIF `Software` tag and the XMP say made a result.
pub const SOFTWARE: &str = concat!("clearview ", env!("CARGO_PKG_VERSION"));

/// The namespace of clearview's XMP properties.
pub const XMP_NS: &str = "http://ns.clearview.invalid/xmp/1.0/";

/// What a decoded photograph carried besides its pixels.
#[derive(Debug, Clone)]
pub struct Metadata {
    /// EXIF as a TIFF structure (no `Exif\0\0` prefix).
    pub exif: Option<Vec<u8>>,
    /// The XMP packet, as stored.
    pub xmp: Option<Vec<u8>>,
    /// IPTC as Photoshop image resources (a JPEG's APP13 after `Photoshop 3.0`).
    pub iptc: Option<Vec<u8>>,
    /// The embedded ICC profile when it was usable (an unusable one is dropped with a
    /// warning), even when it is sRGB: a result carries the keyframe's profile as it was.
    pub icc: Option<Vec<u8>>,
    /// The colour space of the stored pixels.
    pub space: Space,
    /// Bits per stored sample: 8, or 16 for anything deeper (10- and 12-bit HEIC too).
    pub bits: u8,
}

impl Default for Metadata {
    fn default() -> Self {
        Self { exif: None, xmp: None, iptc: None, icc: None, space: Space::Srgb, bits: 8 }
    }
}

/// Where a result came from, for its XMP.
#[derive(Debug, Clone, Default)]
pub struct Provenance {
    /// The report beside the result (`result.json`), as a name relative to the result.
    pub report: Option<String>,
    /// The views that filled pixels of the result, by file name.
    pub views: Vec<String>,
}

/// EXIF bytes without the `Exif\0\0` header some containers (WebP, HEIF, APP1) put first.
pub fn strip_exif_header(bytes: &[u8]) -> &[u8] {
    bytes.strip_prefix(b"Exif\0\0").unwrap_or(bytes)
}

/// The keyframe's EXIF fields as a result keeps them: the primary image's fields (the
/// thumbnail's are dropped), `Orientation` 1, `Software` clearview, the result's pixel size.
pub fn result_fields(exif: &[u8], width: u32, height: u32) -> Result<(Vec<Field>, bool), exif::Error> {
    let parsed = exif::Reader::new().read_raw(strip_exif_header(exif).to_vec())?;
    let replaced = [Tag::Orientation, Tag::Software, Tag::PixelXDimension, Tag::PixelYDimension];
    let mut fields: Vec<Field> = parsed
        .fields()
        .filter(|f| f.ifd_num == In::PRIMARY && !replaced.contains(&f.tag))
        // A value of a type the reader did not know cannot be written back.
        .filter(|f| !matches!(f.value, Value::Unknown(..)))
        .cloned()
        .collect();
    let field = |tag, value| Field { tag, ifd_num: In::PRIMARY, value };
    fields.push(field(Tag::Orientation, Value::Short(vec![1])));
    fields.push(field(Tag::Software, Value::Ascii(vec![SOFTWARE.as_bytes().to_vec()])));
    fields.push(field(Tag::PixelXDimension, Value::Long(vec![width])));
    fields.push(field(Tag::PixelYDimension, Value::Long(vec![height])));
    Ok((fields, parsed.little_endian()))
}

/// The keyframe's EXIF rewritten for a `width × height` result (see [`result_fields`]), as
/// a TIFF structure.
pub fn result_exif(exif: &[u8], width: u32, height: u32) -> Result<Vec<u8>, exif::Error> {
    let (fields, little_endian) = result_fields(exif, width, height)?;
    let write = |fields: &[&Field]| -> Result<Vec<u8>, exif::Error> {
        let mut w = Writer::new();
        for f in fields {
            w.push_field(f);
        }
        let mut out = Cursor::new(Vec::new());
        w.write(&mut out, little_endian)?;
        Ok(out.into_inner())
    };
    let all: Vec<&Field> = fields.iter().collect();
    write(&all).or_else(|_| {
        // A maker note whose values the writer refuses: the rest is worth more than it.
        let kept: Vec<&Field> = fields.iter().filter(|f| f.tag != Tag::MakerNote).collect();
        write(&kept)
    })
}

/// The result's XMP: the keyframe's packet (its `tiff:Orientation` set to 1) with one
/// description of clearview's own added, or a new packet with only that description.
pub fn result_xmp(original: Option<&[u8]>, provenance: &Provenance) -> Vec<u8> {
    let ours = clearview_description(provenance);
    if let Some(text) = original.and_then(|b| std::str::from_utf8(b).ok())
        && let Some(end) = text.rfind("</rdf:RDF>")
    {
        let kept = normalise_orientation(&without_clearview_description(&text[..end]));
        return format!("{kept}{ours}{}", &text[end..]).into_bytes();
    }
    format!(
        "<?xpacket begin=\"\u{feff}\" id=\"W5M0MpCehiHzreSzNTczkc9d\"?>\n\
         <x:xmpmeta xmlns:x=\"adobe:ns:meta/\" x:xmptk=\"{SOFTWARE}\">\n\
         <rdf:RDF xmlns:rdf=\"http://www.w3.org/1999/02/22-rdf-syntax-ns#\">\n{ours}</rdf:RDF>\n\
         </x:xmpmeta>\n<?xpacket end=\"w\"?>"
    )
    .into_bytes()
}

const OURS_START: &str = "<rdf:Description rdf:about=\"\" xmlns:clearview=";

fn clearview_description(p: &Provenance) -> String {
    let mut s = format!(
        "{OURS_START}\"{XMP_NS}\">\n <clearview:Software>{}</clearview:Software>\n",
        escape(SOFTWARE)
    );
    if let Some(r) = &p.report {
        s += &format!(" <clearview:Report>{}</clearview:Report>\n", escape(r));
    }
    s += " <clearview:FilledFrom>\n  <rdf:Bag>\n";
    for v in &p.views {
        s += &format!("   <rdf:li>{}</rdf:li>\n", escape(v));
    }
    s += "  </rdf:Bag>\n </clearview:FilledFrom>\n</rdf:Description>\n";
    s
}

/// `xmp` without a description clearview added before (a result used as a keyframe): its
/// properties would otherwise appear twice.
fn without_clearview_description(xmp: &str) -> String {
    let mut out = xmp.to_owned();
    while let Some(start) = out.find(OURS_START) {
        let Some(len) = out[start..].find("</rdf:Description>") else { break };
        let mut end = start + len + "</rdf:Description>".len();
        if out[end..].starts_with('\n') {
            end += 1;
        }
        out.replace_range(start..end, "");
    }
    out
}

/// `tiff:Orientation` set to 1, as an attribute or as an element.
fn normalise_orientation(xmp: &str) -> String {
    let mut out = String::with_capacity(xmp.len());
    let mut rest = xmp;
    while let Some(i) = rest.find("tiff:Orientation") {
        let after = &rest[i + "tiff:Orientation".len()..];
        out.push_str(&rest[..i + "tiff:Orientation".len()]);
        // Attribute form `tiff:Orientation="6"`, element form `tiff:Orientation>6<`.
        let value_at = if after.starts_with("=\"") || after.starts_with("='") {
            Some(2)
        } else if after.starts_with('>') {
            Some(1)
        } else {
            None
        };
        match value_at {
            Some(k) => {
                let digits = after[k..].bytes().take_while(u8::is_ascii_digit).count();
                out.push_str(&after[..k]);
                out.push('1');
                rest = &after[k + digits..];
            }
            None => rest = after,
        }
    }
    out.push_str(rest);
    out
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera_exif(orientation: u16) -> Vec<u8> {
        let f = |tag, ifd_num, value| Field { tag, ifd_num, value };
        let fields = [
            f(Tag::Make, In::PRIMARY, Value::Ascii(vec![b"Fujifilm".to_vec()])),
            f(Tag::Model, In::PRIMARY, Value::Ascii(vec![b"X-T5".to_vec()])),
            f(Tag::Orientation, In::PRIMARY, Value::Short(vec![orientation])),
            f(Tag::Software, In::PRIMARY, Value::Ascii(vec![b"Digital Camera X-T5 Ver2.00".to_vec()])),
            f(Tag::DateTimeOriginal, In::PRIMARY, Value::Ascii(vec![b"2024:05:17 10:42:07".to_vec()])),
            f(Tag::GPSLatitudeRef, In::PRIMARY, Value::Ascii(vec![b"N".to_vec()])),
            f(
                Tag::GPSLatitude,
                In::PRIMARY,
                Value::Rational(vec![(48, 1).into(), (51, 1).into(), (2950, 100).into()]),
            ),
            f(Tag::Compression, In::THUMBNAIL, Value::Short(vec![6])),
        ];
        let thumb = [0xffu8, 0xd8, 0xff, 0xd9];
        let mut w = Writer::new();
        for x in &fields {
            w.push_field(x);
        }
        w.set_jpeg(&thumb, In::THUMBNAIL);
        let mut out = Cursor::new(Vec::new());
        w.write(&mut out, false).unwrap();
        out.into_inner()
    }

    #[test]
    fn exif_keeps_the_camera_tags_sets_orientation_and_software_and_drops_the_thumbnail() {
        let out = result_exif(&camera_exif(6), 300, 400).unwrap();
        let e = exif::Reader::new().read_raw(out).unwrap();
        let get = |t| e.get_field(t, In::PRIMARY).map(|f| f.display_value().to_string());
        assert_eq!(get(Tag::Make).as_deref(), Some("\"Fujifilm\""));
        assert_eq!(get(Tag::Model).as_deref(), Some("\"X-T5\""));
        assert_eq!(get(Tag::DateTimeOriginal).as_deref(), Some("2024-05-17 10:42:07"));
        assert_eq!(e.get_field(Tag::Orientation, In::PRIMARY).unwrap().value.get_uint(0), Some(1));
        assert_eq!(get(Tag::Software).unwrap(), format!("\"{SOFTWARE}\""));
        assert_eq!(e.get_field(Tag::PixelXDimension, In::PRIMARY).unwrap().value.get_uint(0), Some(300));
        let lat = e.get_field(Tag::GPSLatitude, In::PRIMARY).unwrap();
        assert!(matches!(&lat.value, Value::Rational(v) if v.len() == 3 && v[2].num == 2950));
        assert!(e.fields().all(|f| f.ifd_num == In::PRIMARY), "thumbnail IFD dropped");
        assert!(result_exif(b"Exif\0\0garbage", 1, 1).is_err());
    }

    #[test]
    fn xmp_keeps_the_keyframes_packet_adds_ours_once_and_sets_orientation() {
        let p = Provenance {
            report: Some("result.json".into()),
            views: vec!["a<1>.jpg".into(), "b.heic".into()],
        };
        let fresh = String::from_utf8(result_xmp(None, &p)).unwrap();
        assert!(fresh.contains("<clearview:Report>result.json</clearview:Report>"));
        assert!(
            fresh.contains("<rdf:li>a&lt;1&gt;.jpg</rdf:li>") && fresh.contains("<rdf:li>b.heic</rdf:li>")
        );
        let camera = "<x:xmpmeta xmlns:x=\"adobe:ns:meta/\"><rdf:RDF xmlns:rdf=\"http://www.w3.org/1999/02/22-rdf-syntax-ns#\">\
            <rdf:Description rdf:about=\"\" xmlns:tiff=\"http://ns.adobe.com/tiff/1.0/\" tiff:Orientation=\"6\">\
            <dc:rights>(c) Archive</dc:rights><tiff:Orientation>8</tiff:Orientation></rdf:Description></rdf:RDF></x:xmpmeta>";
        let once = result_xmp(Some(camera.as_bytes()), &p);
        let twice = String::from_utf8(result_xmp(Some(&once), &p)).unwrap();
        assert!(twice.contains("<dc:rights>(c) Archive</dc:rights>"));
        assert_eq!(twice.matches("clearview:Report>result.json").count(), 1, "{twice}");
        assert!(
            twice.contains("tiff:Orientation=\"1\"")
                && twice.contains("<tiff:Orientation>1</tiff:Orientation>")
        );
        assert!(twice.ends_with("</rdf:RDF></x:xmpmeta>"));
    }
}
