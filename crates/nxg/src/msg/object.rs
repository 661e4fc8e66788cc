//! The messages about objects: reading (NXg SW003 §6.1, §6.2, §6.5), writing (§6.3, §6.6),
//! subscribing (§7.1, §7.2) and the pushed changes (§7.3).

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::meta::Hints;
use crate::mplex::Mplex;

/// An mplex as the caller wrote it (an answer echoes that text, docs/PROTOCOL.md §Mplex),
/// checked to be one.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct MplexText {
    /// Index and sub-index.
    pub mplex: Mplex,
    /// The text as it came.
    pub text: String,
}

impl From<Mplex> for MplexText {
    /// The gateway's spelling (`0x` and upper-case hex).
    fn from(mplex: Mplex) -> MplexText {
        MplexText {
            mplex,
            text: mplex.to_string(),
        }
    }
}

impl Serialize for MplexText {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.text)
    }
}

impl<'de> Deserialize<'de> for MplexText {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<MplexText, D::Error> {
        let text = String::deserialize(d)?;
        let mplex = Mplex::parse(&text).map_err(serde::de::Error::custom)?;
        Ok(MplexText { mplex, text })
    }
}

/// The caller's languages for names, hints, lists and error messages (NXg SW003 §6.1.1).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Lang {
    /// First choice (`en`, `de`, …).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preferred_language: Option<String>,
    /// Second choice.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alternate_language: Option<String>,
}

impl Lang {
    /// `preferred`, then `alternate`.
    pub fn new(preferred: &str, alternate: &str) -> Lang {
        Lang {
            preferred_language: Some(preferred.to_owned()),
            alternate_language: Some(alternate.to_owned()),
        }
    }
}

/// A node-ID 1–127.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(transparent)]
pub struct NodeId(u8);

impl NodeId {
    /// `id` if it is 1–127.
    pub fn new(id: u8) -> Option<NodeId> {
        (1..=127).contains(&id).then_some(NodeId(id))
    }

    /// The number.
    pub fn get(self) -> u8 {
        self.0
    }
}

impl<'de> Deserialize<'de> for NodeId {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<NodeId, D::Error> {
        let n = u64::deserialize(d)?;
        u8::try_from(n)
            .ok()
            .and_then(NodeId::new)
            .ok_or_else(|| serde::de::Error::custom(format!("node-ID {n} is not 1–127")))
    }
}

/// Another node than the lift controller (NXg SW003 §6.5, §6.6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct NodeRef {
    /// Node-ID.
    #[cfg_attr(feature = "openapi", schema(value_type = u8, minimum = 1, maximum = 127))]
    pub id: NodeId,
    /// CAN network (1 = the gateway's bus).
    #[serde(default = "net_one")]
    pub net: u8,
    /// Data type of the value, for nodes the gateway has no description of (reads).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub datatype: Option<u32>,
}

fn net_one() -> u8 {
    1
}

impl NodeRef {
    /// Node `id` on network `net`.
    pub fn new(id: NodeId, net: u8) -> NodeRef {
        NodeRef {
            id,
            net,
            datatype: None,
        }
    }
}

/// The `object` of `get_canopen_object`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct GetObject {
    /// Which sub-object (sub-index 1 with `compact`: the whole array).
    pub mplex: MplexText,
    /// All elements of an array at once (§6.2).
    #[serde(default, skip_serializing_if = "is_false")]
    pub compact: bool,
    /// Without names, hints and lists (§6.1.2).
    #[serde(default, skip_serializing_if = "is_false")]
    pub stripped: bool,
    /// Only mplex and value (§6.1.3).
    #[serde(default, skip_serializing_if = "is_false")]
    pub naked: bool,
}

fn is_false(b: &bool) -> bool {
    !*b
}

/// `get_canopen_object` (NXg SW003 §6.1.1, §6.2.1, §6.5.1).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct GetParams {
    /// Languages of names and hints.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lang: Option<Lang>,
    /// Another node than the lift controller.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub node: Option<NodeRef>,
    /// What to read.
    pub object: GetObject,
}

/// The `object` of `put_canopen_object`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PutObject {
    /// Which sub-object.
    pub mplex: MplexText,
    /// The data type the caller assumes (checked against the gateway's).
    pub datatype: u32,
    /// The physical unit the caller assumes (checked too).
    pub physunit: u32,
    /// The value in the connector's text form (docs/PROTOCOL.md §Values).
    pub value: String,
}

/// `put_canopen_object` (NXg SW003 §6.3.1, §6.6.1).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PutParams {
    /// The gateway's serial number, as a check.
    pub sernum: String,
    /// Languages of an error message.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lang: Option<Lang>,
    /// Another node than the lift controller.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub node: Option<NodeRef>,
    /// What to write.
    pub object: PutObject,
}

/// `{"mplex": …}`: which object a put wrote.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Written {
    /// The mplex as the caller wrote it.
    pub mplex: String,
}

/// The answer to `put_canopen_object` (NXg SW003 §6.3.2).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct PutAnswer {
    /// The object written.
    pub object: Written,
}

impl PutAnswer {
    /// The answer for `mplex`.
    pub fn new(mplex: &str) -> PutAnswer {
        PutAnswer {
            object: Written {
                mplex: mplex.to_owned(),
            },
        }
    }
}

/// `{"language": …}` of a full answer: the language names and hints are in.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct AnswerLang {
    /// Language tag.
    pub language: String,
}

/// The `object` of a `get_canopen_object` answer in any of its forms (NXg SW003 §6.1.1–§6.2.2):
/// full (everything), stripped (no `name`, `hint`, `list`), naked (`mplex` and `value` only).
/// Fields a form leaves out are `None`; `min` and `max` are written whenever the metadata is
/// (as `null` when the object has no limit).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ObjectData {
    /// The mplex as the caller wrote it.
    pub mplex: String,
    /// Object code (§8.1).
    #[serde(default)]
    pub objcode: Option<u8>,
    /// Data type (§8.3).
    #[serde(default)]
    pub datatype: Option<u32>,
    /// Presentation form.
    #[serde(default)]
    pub formtype: Option<u32>,
    /// Physical unit (§8.2).
    #[serde(default)]
    pub physunit: Option<u32>,
    /// `rw`, `wo`, `ro` or `const` (§8.5).
    #[serde(default)]
    pub access: Option<String>,
    /// Privilege needed to write (§8.4).
    #[serde(default)]
    pub privilege: Option<u32>,
    /// Name in the answer's language.
    #[serde(default)]
    pub name: Option<String>,
    /// Help text in the answer's language.
    #[serde(default)]
    pub hint: Option<String>,
    /// The value (one element, or every element with `compact`), in text form.
    #[serde(default, deserialize_with = "super::text::many")]
    pub value: Vec<String>,
    /// Lowest value.
    #[serde(default)]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<f64>))]
    pub min: Option<serde_json::Number>,
    /// Highest value (strings: most characters).
    #[serde(default)]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<f64>))]
    pub max: Option<serde_json::Number>,
    /// 0 is valid outside `min..=max`.
    #[serde(default)]
    pub zero: Option<bool>,
    /// Texts for the values (choice) or bits.
    #[serde(default)]
    pub list: Option<Vec<String>>,
}

impl Serialize for ObjectData {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let described = self.objcode.is_some();
        let mut map = s.serialize_map(None)?;
        map.serialize_entry("mplex", &self.mplex)?;
        let optional = [
            ("objcode", self.objcode.map(u32::from)),
            ("datatype", self.datatype),
            ("formtype", self.formtype),
            ("physunit", self.physunit),
        ];
        for (key, value) in optional.iter().filter_map(|(k, v)| v.map(|v| (k, v))) {
            map.serialize_entry(key, &value)?;
        }
        if let Some(access) = &self.access {
            map.serialize_entry("access", access)?;
        }
        if let Some(privilege) = self.privilege {
            map.serialize_entry("privilege", &privilege)?;
        }
        if let Some(name) = &self.name {
            map.serialize_entry("name", name)?;
        }
        if let Some(hint) = &self.hint {
            map.serialize_entry("hint", hint)?;
        }
        map.serialize_entry("value", &self.value)?;
        if described {
            map.serialize_entry("min", &self.min)?;
            map.serialize_entry("max", &self.max)?;
        }
        if let Some(zero) = self.zero {
            map.serialize_entry("zero", &zero)?;
        }
        if let Some(list) = &self.list {
            map.serialize_entry("list", list)?;
        }
        map.end()
    }
}

impl ObjectData {
    /// The value as one text: the single value, or the elements joined with ", ".
    pub fn value_text(&self) -> String {
        self.value.join(", ")
    }
}

/// The answer to `get_canopen_object` (NXg SW003 §6.1.1): `lang` and `hints` only in the full
/// form.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ObjectAnswer {
    /// The language of names and hints.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lang: Option<AnswerLang>,
    /// The object.
    pub object: ObjectData,
    /// Presentation hints.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hints: Option<Hints>,
}

/// `reg_canopen_object` (NXg SW003 §7.1.1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RegParams {
    /// The objects; all or none are registered.
    pub mplex: Vec<MplexText>,
    /// Minimum gap between two pushes of one object (ms).
    #[serde(default)]
    pub inhibit: u64,
    /// Smallest change (absolute) of a number that is pushed. Written as an integer when it is
    /// one (`"threshold": 1`, as NXg §7.1's sample has it), not `1.0`.
    #[serde(
        default,
        deserialize_with = "non_negative",
        serialize_with = "integer_when_integral"
    )]
    pub threshold: f64,
    /// Another node than the lift controller.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub node: Option<NodeRef>,
}

fn integer_when_integral<S: serde::Serializer>(t: &f64, s: S) -> Result<S::Ok, S::Error> {
    // Exact as an integer up to 2⁵³, as JSON numbers are read.
    if t.fract() == 0.0 && t.abs() < 9_007_199_254_740_992.0 {
        s.serialize_i64(*t as i64)
    } else {
        s.serialize_f64(*t)
    }
}

fn non_negative<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    let t = f64::deserialize(d)?;
    if t >= 0.0 {
        Ok(t)
    } else {
        Err(serde::de::Error::custom("threshold is a number ≥ 0"))
    }
}

/// `unreg_canopen_object` (NXg SW003 §7.2.1).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct UnregParams {
    /// The objects.
    pub mplex: Vec<MplexText>,
    /// Another node than the lift controller.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub node: Option<NodeRef>,
}

/// The payload of a `canopen_object` notification (NXg SW003 §7.3.1); pushes of other nodes
/// than the lift controller say which node they are from.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Notification {
    /// The object (the gateway's spelling).
    pub mplex: String,
    /// Its new value in text form.
    #[serde(deserialize_with = "super::text::one")]
    pub value: String,
    /// Another node than the lift controller.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub node: Option<NodeRef>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn requests_of_the_specification_read() {
        let get: GetParams = serde_json::from_str(
            r#"{"lang":{"preferred_language":"en","alternate_language":"de"},
               "node":{"id":12,"net":1,"datatype":25},"object":{"mplex":"0x610001","compact":false}}"#,
        )
        .unwrap();
        assert_eq!(get.node.map(|n| (n.id.get(), n.net)), Some((12, 1)));
        assert_eq!(
            get.object.mplex.mplex,
            Mplex {
                index: 0x6100,
                sub: 1
            }
        );
        let put: PutParams = serde_json::from_str(
            r#"{"sernum":"180917010200000102","node":{"id":12,"net":1},
               "object":{"mplex":"0x502200","datatype":7,"physunit":0,"value":"4"}}"#,
        )
        .unwrap();
        assert_eq!(put.object.value, "4");
        let reg: RegParams = serde_json::from_str(
            r#"{"mplex":["0x652001","0x652002"],"inhibit":1000,"threshold":1}"#,
        )
        .unwrap();
        assert_eq!(
            (reg.mplex.len(), reg.inhibit, reg.threshold),
            (2, 1000, 1.0)
        );
        assert!(serde_json::from_str::<RegParams>(r#"{"mplex":[],"threshold":-1}"#).is_err());
        // Written as the sample writes it: an integer when it is one.
        let text = serde_json::to_string(&reg).unwrap();
        assert!(text.ends_with(r#""inhibit":1000,"threshold":1}"#), "{text}");
        let half = RegParams {
            threshold: 0.5,
            ..reg.clone()
        };
        assert!(serde_json::to_string(&half)
            .unwrap()
            .contains(r#""threshold":0.5"#));
        assert!(serde_json::from_str::<NodeRef>(r#"{"id":128}"#).is_err());
        assert!(serde_json::from_str::<NodeRef>(r#"{"id":0}"#).is_err());
        // The caller's spelling is kept for the answer.
        let m: MplexText = serde_json::from_str(r#""0x63b0ff""#).unwrap();
        assert_eq!(serde_json::to_string(&m).unwrap(), r#""0x63b0ff""#);
    }

    #[test]
    fn answers_in_every_form() {
        let naked = ObjectAnswer {
            object: ObjectData {
                mplex: "0x652001".into(),
                value: vec!["2510".into()],
                ..ObjectData::default()
            },
            ..ObjectAnswer::default()
        };
        assert_eq!(
            serde_json::to_value(&naked).unwrap(),
            json!({"object":{"mplex":"0x652001","value":["2510"]}})
        );
        let stripped = ObjectData {
            objcode: Some(7),
            datatype: Some(9),
            formtype: Some(1),
            physunit: Some(0),
            access: Some("ro".into()),
            privilege: Some(0),
            zero: Some(false),
            ..naked.object.clone()
        };
        assert_eq!(
            serde_json::to_value(&stripped).unwrap(),
            json!({"mplex":"0x652001","objcode":7,"datatype":9,"formtype":1,"physunit":0,
                   "access":"ro","privilege":0,"value":["2510"],"min":null,"max":null,"zero":false})
        );
        let read: ObjectData =
            serde_json::from_value(json!({"mplex":"0x1","value":[5, "x"]})).unwrap();
        assert_eq!(read.value, ["5", "x"]);
        let n: Notification =
            serde_json::from_value(json!({"mplex":"0x652001","value":2510})).unwrap();
        assert_eq!(n.value, "2510");
    }
}
