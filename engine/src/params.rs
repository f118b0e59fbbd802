//! Plan parameters: values a plan script reads with `param("name", default)` and that the
//! command line (`--param name=value`) or a sweep (`param.name` keys) sets from outside, so
//! that one script can be run, compared and swept at several settings without editing it.
//!
//! A parameter's type is its default's: an integer, a number, a boolean or a string. Units are
//! the script's business (`mm(param("standoff_mm", 12))`), so the name should say them.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;

/// A parameter's value, as given from outside or as the plan used it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum ParamValue {
    /// A whole number.
    Int(i64),
    /// A number.
    Float(f64),
    /// A boolean.
    Bool(bool),
    /// A string, or a command line's text not yet read as the default's type.
    Text(String),
}

impl fmt::Display for ParamValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Int(i) => write!(f, "{i}"),
            Self::Float(x) => write!(f, "{x:?}"),
            Self::Bool(b) => write!(f, "{b}"),
            Self::Text(s) => write!(f, "{s:?}"),
        }
    }
}

/// Parameters given from outside a plan, by name.
pub type Params = BTreeMap<String, ParamValue>;

/// Whether `name` may name a parameter: ASCII letters, digits and `_`, not starting with a
/// digit (so it reads the same on a command line, in a TOML key and in a script).
pub fn valid_param_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 64
        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        && !name.starts_with(|c: char| c.is_ascii_digit())
}

/// `NAME=VALUE`, as `--param` takes it: the value stays text until the plan's default says
/// what type it must be.
pub fn parse_param_arg(arg: &str) -> Result<(String, ParamValue), String> {
    let (name, value) = arg
        .split_once('=')
        .ok_or_else(|| format!("{arg:?}: expected NAME=VALUE, e.g. standoff_mm=12"))?;
    let name = name.trim();
    if !valid_param_name(name) {
        return Err(format!(
            "{name:?}: a parameter's name is ASCII letters, digits and _, not starting with a digit"
        ));
    }
    Ok((name.to_string(), ParamValue::Text(value.to_string())))
}

/// `given`, read as the type of `default` for the parameter `name`.
pub(crate) fn coerce(
    name: &str,
    given: &ParamValue,
    default: &ParamValue,
) -> Result<ParamValue, String> {
    let wrong = |expected: &str| {
        Err(format!(
            "param {name:?} was given {given}, but its default {default} makes it {expected}"
        ))
    };
    match (default, given) {
        (ParamValue::Int(_), ParamValue::Int(i)) => Ok(ParamValue::Int(*i)),
        (ParamValue::Int(_), ParamValue::Text(s)) => match s.trim().parse::<i64>() {
            Ok(i) => Ok(ParamValue::Int(i)),
            Err(_) => wrong("an integer"),
        },
        (ParamValue::Int(_), _) => wrong("an integer"),
        (ParamValue::Float(_), v) => {
            let x = match v {
                ParamValue::Int(i) => *i as f64,
                ParamValue::Float(x) => *x,
                ParamValue::Text(s) => match s.trim().parse::<f64>() {
                    Ok(x) => x,
                    Err(_) => return wrong("a number"),
                },
                ParamValue::Bool(_) => return wrong("a number"),
            };
            if x.is_finite() {
                Ok(ParamValue::Float(x))
            } else {
                wrong("a finite number")
            }
        }
        (ParamValue::Bool(_), ParamValue::Bool(b)) => Ok(ParamValue::Bool(*b)),
        (ParamValue::Bool(_), ParamValue::Text(s)) => match s.trim() {
            "true" => Ok(ParamValue::Bool(true)),
            "false" => Ok(ParamValue::Bool(false)),
            _ => wrong("a boolean (true or false)"),
        },
        (ParamValue::Bool(_), _) => wrong("a boolean (true or false)"),
        (ParamValue::Text(_), ParamValue::Text(s)) => Ok(ParamValue::Text(s.clone())),
        (ParamValue::Text(_), _) => wrong("a string"),
    }
}

/// What the `param` calls of one evaluation saw: the values given, and each parameter the
/// script declared with its default and the value it got.
#[derive(Debug, Default)]
pub(crate) struct ParamState {
    pub given: Params,
    /// Name → (default, value used).
    pub declared: BTreeMap<String, (ParamValue, ParamValue)>,
}

impl ParamState {
    /// The value of `name` with `default`: the given one read as the default's type, or the
    /// default. A second declaration must repeat the first's default.
    pub fn get(&mut self, name: &str, default: ParamValue) -> Result<ParamValue, String> {
        if !valid_param_name(name) {
            return Err(format!(
                "param({name:?}, ..): a parameter's name is ASCII letters, digits and _, not \
                 starting with a digit"
            ));
        }
        if let ParamValue::Float(x) = default {
            if !x.is_finite() {
                return Err(format!("param({name:?}, {x}): the default must be finite"));
            }
        }
        if let Some((first, used)) = self.declared.get(name) {
            if *first != default {
                return Err(format!(
                    "param({name:?}, {default}): declared before with the default {first}; \
                     give one default"
                ));
            }
            return Ok(used.clone());
        }
        let used = match self.given.get(name) {
            Some(v) => coerce(name, v, &default)?,
            None => default.clone(),
        };
        self.declared
            .insert(name.to_string(), (default, used.clone()));
        Ok(used)
    }
}

/// A parameter as a plan declared it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DeclaredParam {
    /// The script's default.
    pub default: ParamValue,
    /// The value the plan was built with.
    pub value: ParamValue,
    /// Whether `value` was given from outside (else it is the default).
    pub given: bool,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_is_read_as_the_defaults_type() {
        let t = |s: &str| ParamValue::Text(s.into());
        assert_eq!(
            coerce("a", &t("3"), &ParamValue::Int(1)),
            Ok(ParamValue::Int(3))
        );
        assert_eq!(
            coerce("a", &t("2.5"), &ParamValue::Float(1.0)),
            Ok(ParamValue::Float(2.5))
        );
        assert_eq!(
            coerce("a", &ParamValue::Int(2), &ParamValue::Float(1.0)),
            Ok(ParamValue::Float(2.0))
        );
        assert_eq!(
            coerce("a", &t("true"), &ParamValue::Bool(false)),
            Ok(ParamValue::Bool(true))
        );
        assert_eq!(coerce("a", &t("12"), &t("x")), Ok(t("12")));
        let e = coerce("a", &t("2.5"), &ParamValue::Int(1)).expect_err("not an integer");
        assert!(e.contains("an integer"), "{e}");
        let e = coerce("a", &t("inf"), &ParamValue::Float(1.0)).expect_err("not finite");
        assert!(e.contains("finite"), "{e}");
        let e = coerce("a", &ParamValue::Float(3.0), &ParamValue::Int(1)).expect_err("a float");
        assert!(e.contains("an integer"), "{e}");
        let e = coerce("a", &ParamValue::Int(3), &t("x")).expect_err("not a string");
        assert!(e.contains("a string"), "{e}");
    }

    #[test]
    fn names_and_arguments() {
        assert_eq!(
            parse_param_arg("standoff_mm=12"),
            Ok(("standoff_mm".into(), ParamValue::Text("12".into())))
        );
        assert_eq!(
            parse_param_arg("label=a=b"),
            Ok(("label".into(), ParamValue::Text("a=b".into())))
        );
        for bad in ["standoff", "=3", "1a=3", "a.b=3", "a b=3"] {
            assert!(parse_param_arg(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn a_second_declaration_repeats_the_default() {
        let mut s = ParamState::default();
        s.given.insert("n".into(), ParamValue::Int(4));
        assert_eq!(s.get("n", ParamValue::Int(2)), Ok(ParamValue::Int(4)));
        assert_eq!(s.get("n", ParamValue::Int(2)), Ok(ParamValue::Int(4)));
        assert!(s.get("n", ParamValue::Int(3)).is_err());
        assert_eq!(
            s.get("m", ParamValue::Float(0.5)),
            Ok(ParamValue::Float(0.5))
        );
        assert!(s.get("bad name", ParamValue::Int(1)).is_err());
    }
}
