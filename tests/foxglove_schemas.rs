//! The hand-written JSON schemas of the Foxglove well-known messages flownav logs
//! (`src/logging/foxglove.rs`) against the official definitions: the protobuf descriptors that
//! Foxglove's own SDK (the `foxglove` crate) ships for the same messages. Every property a
//! schema declares, at every depth, must be a field of the official message with a compatible
//! type, and every enumeration must name the official values; otherwise Foxglove's panels and
//! message paths would not find what flownav writes. Fields named `flownav_*` are flownav's own
//! extensions (Foxglove ignores fields it does not know).

use flownav::logging::foxglove as ours;
use foxglove::Encode;
use prost::Message;
use prost_types::field_descriptor_proto::{Label, Type};
use prost_types::{DescriptorProto, EnumDescriptorProto, FileDescriptorSet};
use serde_json::Value;
use std::collections::HashMap;

/// The official message and enum definitions, by full name (`foxglove.CompressedImage`,
/// `google.protobuf.Timestamp`, ...).
#[derive(Default)]
struct Official {
    messages: HashMap<String, DescriptorProto>,
    enums: HashMap<String, EnumDescriptorProto>,
}

impl Official {
    fn add<T: Encode>(&mut self) {
        let schema = T::get_schema().expect("the SDK's well-known messages carry their schema");
        assert_eq!(schema.encoding, "protobuf");
        let set = FileDescriptorSet::decode(&*schema.data).expect("a protobuf FileDescriptorSet");
        for file in set.file {
            let package = file.package.clone().unwrap_or_default();
            for m in file.message_type {
                for e in &m.enum_type {
                    self.enums.insert(format!("{package}.{}.{}", m.name(), e.name()), e.clone());
                }
                self.messages.insert(format!("{package}.{}", m.name()), m);
            }
            for e in file.enum_type {
                self.enums.insert(format!("{package}.{}", e.name()), e);
            }
        }
    }
}

fn official() -> Official {
    use foxglove::messages::*;
    let mut o = Official::default();
    o.add::<CompressedImage>();
    o.add::<RawImage>();
    o.add::<CameraCalibration>();
    o.add::<ImageAnnotations>();
    o.add::<FrameTransform>();
    o.add::<SceneUpdate>();
    o.add::<Log>();
    o
}

/// Checks `schema` (a JSON schema object titled with the message's full name) against the
/// official message `name`, recursively; returns the checked paths.
fn check_message(o: &Official, name: &str, schema: &Value, path: &str, checked: &mut Vec<String>) {
    let message = o.messages.get(name).unwrap_or_else(|| panic!("{path}: no official message {name}"));
    let properties = schema["properties"].as_object().unwrap_or_else(|| panic!("{path}: no properties"));
    for (field_name, field_schema) in properties {
        let at = format!("{path}.{field_name}");
        if field_name.starts_with("flownav_") {
            // flownav's own extension of a well-known message (Foxglove ignores fields it does
            // not know): it must say so
            let description = field_schema["description"].as_str().unwrap_or_default();
            assert!(description.starts_with("flownav extension"), "{at}: an extension must be described as one");
            checked.push(format!("{at} (extension)"));
            continue;
        }
        let field = message
            .field
            .iter()
            .find(|f| f.name() == field_name)
            .unwrap_or_else(|| panic!("{at}: {name} has no field {field_name:?}"));
        let repeated = field.label() == Label::Repeated;
        let declared = field_schema["type"].as_str();
        let element = if repeated {
            assert_eq!(declared, Some("array"), "{at}: official field is repeated");
            if field_schema.get("items").is_none() {
                // an array flownav always writes empty (the primitives it never draws)
                checked.push(format!("{at} (empty)"));
                continue;
            }
            &field_schema["items"]
        } else {
            field_schema
        };
        check_field(o, field, element, &at, checked);
        checked.push(at);
    }
}

fn check_field(
    o: &Official,
    field: &prost_types::FieldDescriptorProto,
    schema: &Value,
    at: &str,
    checked: &mut Vec<String>,
) {
    let declared = schema["type"].as_str();
    let type_name = field.type_name().trim_start_matches('.');
    match field.r#type() {
        Type::Double | Type::Float => assert_eq!(declared, Some("number"), "{at}: official {:?}", field.r#type()),
        Type::Int32 | Type::Int64 | Type::Sint32 | Type::Sint64 | Type::Sfixed32 | Type::Sfixed64 => {
            assert!(
                matches!(declared, Some("integer" | "number")),
                "{at}: official {:?}, declared {declared:?}",
                field.r#type()
            )
        }
        Type::Uint32 | Type::Uint64 | Type::Fixed32 | Type::Fixed64 => {
            assert!(
                matches!(declared, Some("integer" | "number")),
                "{at}: official {:?}, declared {declared:?}",
                field.r#type()
            );
            if declared == Some("integer") {
                assert!(schema["minimum"].as_f64().is_some_and(|m| m >= 0.0), "{at}: unsigned, but negatives allowed");
            }
        }
        Type::Bool => assert_eq!(declared, Some("boolean"), "{at}"),
        Type::String => assert_eq!(declared, Some("string"), "{at}"),
        Type::Bytes => {
            assert_eq!(declared, Some("string"), "{at}: bytes are base64 strings in JSON");
            assert_eq!(schema["contentEncoding"], "base64", "{at}");
        }
        Type::Enum => {
            let official = o.enums.get(type_name).unwrap_or_else(|| panic!("{at}: no official enum {type_name}"));
            let values = schema["oneOf"].as_array().unwrap_or_else(|| panic!("{at}: an enum, declared without oneOf"));
            for v in values {
                let (title, number) = (v["title"].as_str().unwrap(), v["const"].as_i64().unwrap());
                let found = official.value.iter().find(|e| e.name() == title);
                assert_eq!(
                    found.map(|e| i64::from(e.number())),
                    Some(number),
                    "{at}: {type_name} value {title} = {number}"
                );
            }
            checked.push(format!("{at} ({} values)", values.len()));
        }
        Type::Message => match type_name {
            "google.protobuf.Timestamp" | "google.protobuf.Duration" => {
                let props = schema["properties"].as_object().unwrap_or_else(|| panic!("{at}: a time, no properties"));
                let mut keys: Vec<&str> = props.keys().map(String::as_str).collect();
                keys.sort_unstable();
                assert_eq!(keys, ["nsec", "sec"], "{at}: Foxglove's JSON time is {{sec, nsec}}");
            }
            _ => {
                let title = schema["title"].as_str().unwrap_or_default();
                assert_eq!(title, type_name, "{at}: declared as {title:?}, officially {type_name}");
                check_message(o, type_name, schema, at, checked);
            }
        },
        other => panic!("{at}: official type {other:?} not expected in these messages"),
    }
}

#[test]
fn the_logged_foxglove_schemas_match_the_official_definitions() {
    let o = official();
    let schemas = [
        ours::compressed_image_schema(),
        ours::raw_image_schema(),
        ours::camera_calibration_schema(),
        ours::image_annotations_schema(),
        ours::frame_transform_schema(),
        ours::scene_update_schema(),
        ours::log_schema(),
    ];
    let mut checked = Vec::new();
    for schema in &schemas {
        let name = schema["title"].as_str().expect("a schema titled with the message's full name");
        check_message(&o, name, schema, name, &mut checked);
    }
    // the check reached the nested types, not only the top level
    for deep in [
        "foxglove.ImageAnnotations.points.outline_colors.a",
        "foxglove.SceneUpdate.entities.cubes.pose.orientation.w",
        "foxglove.FrameTransform.timestamp",
        "foxglove.Log.level (6 values)",
    ] {
        assert!(checked.iter().any(|c| c == deep), "{deep} not checked: {checked:#?}");
    }
}

#[test]
fn a_wrong_field_is_caught() {
    let o = official();
    let mut bad = ours::log_schema();
    bad["properties"]["mesage"] = bad["properties"]["message"].clone();
    let caught = std::panic::catch_unwind(|| check_message(&o, "foxglove.Log", &bad, "foxglove.Log", &mut Vec::new()));
    assert!(caught.is_err(), "a misspelt field must fail the check");
    let mut bad = ours::log_schema();
    bad["properties"]["level"]["oneOf"][2]["const"] = 7.into();
    let caught = std::panic::catch_unwind(|| check_message(&o, "foxglove.Log", &bad, "foxglove.Log", &mut Vec::new()));
    assert!(caught.is_err(), "a wrong enum number must fail the check");
}
