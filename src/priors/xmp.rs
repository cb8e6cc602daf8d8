//! DJI's XMP attributes (`drone-dji:GimbalYawDegree="+45.00"` …), read by hand from the packet's
//! text: no XML library for a dozen numbers. Both RDF spellings are accepted, the attribute
//! (`drone-dji:Name="v"`, single or double quotes) and the element
//! (`<drone-dji:Name>v</drone-dji:Name>`). A missing attribute is `None`; a present one that is not
//! a number is an error carrying what was found.

use std::collections::BTreeMap;

const PREFIX: &str = "drone-dji:";

/// The `drone-dji:` attributes of one XMP packet, by name without the prefix.
#[derive(Debug, Default, PartialEq)]
pub struct DjiXmp {
    pub attributes: BTreeMap<String, String>,
}

impl DjiXmp {
    pub fn parse(packet: &str) -> Self {
        let mut attributes = BTreeMap::new();
        let mut rest = packet;
        while let Some(start) = rest.find(PREFIX) {
            let preceding = rest[..start].chars().next_back();
            let after = &rest[start + PREFIX.len()..];
            let name_len = after
                .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_' || c == '-'))
                .unwrap_or(after.len());
            let name = &after[..name_len];
            let tail = &after[name_len..];
            rest = tail;
            if name.is_empty() {
                continue;
            }
            if preceding == Some('<') {
                // Element form: <drone-dji:Name>value</drone-dji:Name> (a closing tag has '/').
                if let Some(body) = tail.strip_prefix('>') {
                    if let Some(end) = body.find('<') {
                        attributes
                            .entry(name.to_string())
                            .or_insert_with(|| body[..end].trim().to_string());
                    }
                }
                continue;
            }
            if preceding == Some('/') {
                continue;
            }
            // Attribute form: Name = "value" (whitespace around '=' is allowed by XML).
            let Some(eq) = tail.trim_start().strip_prefix('=') else {
                continue;
            };
            let eq = eq.trim_start();
            let Some(quote) = eq.chars().next().filter(|c| *c == '"' || *c == '\'') else {
                continue;
            };
            if let Some(end) = eq[1..].find(quote) {
                attributes
                    .entry(name.to_string())
                    .or_insert_with(|| eq[1..1 + end].trim().to_string());
            }
        }
        Self { attributes }
    }

    /// The attribute as a number: `Ok(None)` when absent, `Err(text)` when not a finite number.
    pub fn number(&self, name: &str) -> Result<Option<f64>, String> {
        match self.attributes.get(name) {
            None => Ok(None),
            Some(text) => text
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .map(Some)
                .ok_or_else(|| format!("\"{text}\"")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An excerpt of a Phantom 4's XMP packet (attribute form), as DJI writes it.
    const PHANTOM: &str = r#"<?xpacket begin="" id="W5M0MpCehiHzreSzNTczkc9d"?>
<x:xmpmeta xmlns:x="adobe:ns:meta/">
 <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">
  <rdf:Description rdf:about="DJI Meta Data"
    xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"
   drone-dji:AbsoluteAltitude="+198.51"
   drone-dji:RelativeAltitude="+40.00"
   drone-dji:GimbalRollDegree="+0.00"
   drone-dji:GimbalYawDegree="-132.00"
   drone-dji:GimbalPitchDegree="-89.90"
   drone-dji:FlightRollDegree="+0.90"
   drone-dji:FlightYawDegree="-129.90"
   drone-dji:FlightPitchDegree="-1.60">
  </rdf:Description>
 </rdf:RDF>
</x:xmpmeta>"#;

    #[test]
    fn attribute_form() {
        let xmp = DjiXmp::parse(PHANTOM);
        assert_eq!(xmp.number("GimbalYawDegree"), Ok(Some(-132.0)));
        assert_eq!(xmp.number("GimbalPitchDegree"), Ok(Some(-89.9)));
        assert_eq!(xmp.number("GimbalRollDegree"), Ok(Some(0.0)));
        assert_eq!(xmp.number("RelativeAltitude"), Ok(Some(40.0)));
        assert_eq!(xmp.number("FlightPitchDegree"), Ok(Some(-1.6)));
        assert_eq!(xmp.number("CamReverse"), Ok(None));
        assert_eq!(xmp.attributes.len(), 8, "{:?}", xmp.attributes);
    }

    #[test]
    fn element_form_single_quotes_and_spaces() {
        let xmp = DjiXmp::parse(
            "<rdf:Description drone-dji:GimbalYawDegree = '12.5'>\
             <drone-dji:GimbalPitchDegree>-90.0</drone-dji:GimbalPitchDegree>\
             <drone-dji:GimbalRollDegree> 0.2 </drone-dji:GimbalRollDegree></rdf:Description>",
        );
        assert_eq!(xmp.number("GimbalYawDegree"), Ok(Some(12.5)));
        assert_eq!(xmp.number("GimbalPitchDegree"), Ok(Some(-90.0)));
        assert_eq!(xmp.number("GimbalRollDegree"), Ok(Some(0.2)));
        assert_eq!(xmp.attributes.len(), 3);
    }

    #[test]
    fn malformed_values_and_garbage() {
        let xmp = DjiXmp::parse(r#"drone-dji:GimbalYawDegree="north" drone-dji:X="nan""#);
        assert_eq!(xmp.number("GimbalYawDegree"), Err("\"north\"".to_string()));
        assert!(xmp.number("X").is_err());
        // Truncated packets and stray prefixes do not panic and give nothing.
        for text in [
            "drone-dji:",
            "drone-dji:A=",
            "drone-dji:A=\"1",
            "<drone-dji:A>1",
            "x drone-dji:=1",
        ] {
            assert!(DjiXmp::parse(text).attributes.is_empty(), "{text}");
        }
        assert!(DjiXmp::parse("").attributes.is_empty());
    }
}
