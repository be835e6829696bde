//! How a [`Command`] reads: as the variant of an [`Edit`] or an [`Output`],
//! exactly as when they were one enum (same names, same messages: an
//! unknown name lists every command). The variant name is read first, then
//! the rest goes to the derived reader of whichever enum has that name.

use super::{Command, Edit, Output};
use serde::de::{self, Deserialize, Deserializer, EnumAccess, IntoDeserializer, VariantAccess, Visitor};
use std::sync::OnceLock;

impl<'de> Deserialize<'de> for Command {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_enum("Command", all_variants(), CommandVisitor)
    }
}

/// The variant names of `Edit` then `Output` (the order of the old enum).
fn all_variants() -> &'static [&'static str] {
    static ALL: OnceLock<Vec<&'static str>> = OnceLock::new();
    ALL.get_or_init(|| [variants::<Edit>(), variants::<Output>()].concat())
}

struct CommandVisitor;

impl<'de> Visitor<'de> for CommandVisitor {
    type Value = Command;
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("enum Command")
    }
    fn visit_enum<A: EnumAccess<'de>>(self, data: A) -> Result<Command, A::Error> {
        let (Ident(tag), variant): (Ident, A::Variant) = data.variant()?;
        if variants::<Edit>().contains(&tag.as_str()) {
            Edit::deserialize(Replay { tag, variant }).map(Command::Edit)
        } else if variants::<Output>().contains(&tag.as_str()) {
            Output::deserialize(Replay { tag, variant }).map(Command::Output)
        } else {
            Err(de::Error::unknown_variant(&tag, all_variants()))
        }
    }
}

/// A variant name, read as an identifier (RON spells it bare).
struct Ident(String);

impl<'de> Deserialize<'de> for Ident {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl Visitor<'_> for V {
            type Value = Ident;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a command name")
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<Ident, E> {
                Ok(Ident(v.to_string()))
            }
        }
        d.deserialize_identifier(V)
    }
}

/// An enum whose variant name was already read: hands the name and the
/// rest of the variant to a derived enum reader.
struct Replay<V> {
    tag: String,
    variant: V,
}

impl<'de, A: VariantAccess<'de>> Deserializer<'de> for Replay<A> {
    type Error = A::Error;
    fn deserialize_any<W: Visitor<'de>>(self, visitor: W) -> Result<W::Value, A::Error> {
        visitor.visit_enum(self)
    }
    serde::forward_to_deserialize_any! {
        bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf option unit
        unit_struct newtype_struct seq tuple tuple_struct map struct enum identifier ignored_any
    }
}

impl<'de, A: VariantAccess<'de>> EnumAccess<'de> for Replay<A> {
    type Error = A::Error;
    type Variant = A;
    fn variant_seed<S: de::DeserializeSeed<'de>>(self, seed: S) -> Result<(S::Value, A), A::Error> {
        let name = seed.deserialize(self.tag.into_deserializer())?;
        Ok((name, self.variant))
    }
}

/// The variant names a derived enum reader declares (it passes them to
/// `deserialize_enum`; this deserializer catches them and stops).
fn variants<'de, T: Deserialize<'de>>() -> &'static [&'static str] {
    match T::deserialize(VariantNames) {
        Err(Caught(Some(v))) => v,
        _ => &[],
    }
}

struct VariantNames;

#[derive(Debug)]
struct Caught(Option<&'static [&'static str]>);

impl std::fmt::Display for Caught {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("variant names")
    }
}
impl std::error::Error for Caught {}
impl de::Error for Caught {
    fn custom<T: std::fmt::Display>(_: T) -> Self {
        Caught(None)
    }
}

impl<'de> Deserializer<'de> for VariantNames {
    type Error = Caught;
    fn deserialize_any<W: Visitor<'de>>(self, _: W) -> Result<W::Value, Caught> {
        Err(Caught(None))
    }
    fn deserialize_enum<W: Visitor<'de>>(
        self,
        _: &'static str,
        variants: &'static [&'static str],
        _: W,
    ) -> Result<W::Value, Caught> {
        Err(Caught(Some(variants)))
    }
    serde::forward_to_deserialize_any! {
        bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf option unit
        unit_struct newtype_struct seq tuple tuple_struct map struct identifier ignored_any
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_command_name_belongs_to_one_kind() {
        let (e, o) = (variants::<Edit>(), variants::<Output>());
        assert!(e.contains(&"stroke") && e.contains(&"load_field"), "{e:?}");
        assert_eq!(o, ["render", "export"]);
        assert!(e.iter().all(|n| !o.contains(n)));
    }

    #[test]
    fn edits_and_outputs_read_as_before() {
        let c: Command = serde_json::from_str(r#"{"remove": {"object": "pot"}}"#).unwrap();
        assert_eq!(c, Command::Edit(Edit::Remove { object: "pot".into() }));
        let c: Command = ron::from_str(r#"export(script(out: "s.ron"))"#).unwrap();
        assert_eq!(c.kind(), "export");
        assert_eq!(
            serde_json::to_string(&c).unwrap(),
            r#"{"export":{"script":{"out":"s.ron"}}}"#
        );
        let e = serde_json::from_str::<Command>(r#"{"strok": {}}"#)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("unknown variant `strok`, expected one of `load_field`"),
            "{e}"
        );
        assert!(e.contains("`render`, `export`"), "{e}");
        let e = serde_json::from_str::<Command>(r#"{"remove": {"objet": "pot"}}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown field `objet`"), "{e}");
    }
}
