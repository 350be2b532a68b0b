//! Rule expressions: a small hand-written parser for the `if` and `then` texts of a rule, and
//! the compiled, allocation-free form the engine evaluates.
//!
//! Grammar (keywords `is`, `not`, `and`, `or` are case-insensitive; `and` binds tighter than
//! `or`; parentheses nest):
//!
//! ```text
//! antecedent := or
//! or         := and ("or" and)*
//! and        := unary ("and" unary)*
//! unary      := "not" unary | "(" or ")" | clause
//! clause     := VARIABLE "is" ["not"] TERM
//! consequent := VARIABLE "is" TERM ("and" VARIABLE "is" TERM)*
//! ```

/// A parse error: what was expected and the 0-based character position in the rule text.
#[derive(Clone, Debug, PartialEq)]
pub struct ParseError {
    pub position: usize,
    pub message: String,
}

/// A parsed antecedent, with names still unresolved (positions kept for error messages).
#[derive(Clone, Debug, PartialEq)]
pub enum Expr {
    /// `variable is term`, with the character positions of both names.
    Is {
        variable: String,
        variable_at: usize,
        term: String,
        term_at: usize,
    },
    Not(Box<Expr>),
    And(Vec<Expr>),
    Or(Vec<Expr>),
}

/// One `variable is term` of a consequent.
#[derive(Clone, Debug, PartialEq)]
pub struct Assignment {
    pub variable: String,
    pub variable_at: usize,
    pub term: String,
    pub term_at: usize,
}

#[derive(Clone, Debug, PartialEq)]
enum Tok<'a> {
    Word(&'a str),
    Open,
    Close,
}

fn tokenize(text: &str) -> Result<Vec<(Tok<'_>, usize)>, ParseError> {
    let mut out = Vec::new();
    let mut chars = text.char_indices().peekable();
    while let Some(&(i, ch)) = chars.peek() {
        if ch.is_whitespace() {
            chars.next();
        } else if ch == '(' {
            out.push((Tok::Open, i));
            chars.next();
        } else if ch == ')' {
            out.push((Tok::Close, i));
            chars.next();
        } else if ch.is_alphanumeric() || ch == '_' {
            let mut end = i;
            while let Some(&(j, c)) = chars.peek() {
                if c.is_alphanumeric() || c == '_' || c == '-' {
                    end = j + c.len_utf8();
                    chars.next();
                } else {
                    break;
                }
            }
            out.push((Tok::Word(&text[i..end]), i));
        } else {
            return Err(ParseError {
                position: text[..i].chars().count(),
                message: format!("unexpected character '{ch}' (use names, 'is', 'not', 'and', 'or' and parentheses)"),
            });
        }
    }
    // Report positions in characters, not bytes.
    Ok(out.into_iter().map(|(t, i)| (t, text[..i].chars().count())).collect())
}

struct Parser<'a> {
    toks: Vec<(Tok<'a>, usize)>,
    at: usize,
    end: usize,
}

fn is_keyword(w: &str, k: &str) -> bool {
    w.eq_ignore_ascii_case(k)
}

fn is_any_keyword(w: &str) -> bool {
    ["is", "not", "and", "or"].iter().any(|k| is_keyword(w, k))
}

impl<'a> Parser<'a> {
    fn new(text: &'a str) -> Result<Self, ParseError> {
        Ok(Parser { toks: tokenize(text)?, at: 0, end: text.chars().count() })
    }

    fn peek(&self) -> Option<&(Tok<'a>, usize)> {
        self.toks.get(self.at)
    }

    fn pos(&self) -> usize {
        self.peek().map_or(self.end, |t| t.1)
    }

    fn describe(&self) -> String {
        match self.peek() {
            None => "the end of the text".to_string(),
            Some((Tok::Open, _)) => "'('".to_string(),
            Some((Tok::Close, _)) => "')'".to_string(),
            Some((Tok::Word(w), _)) => format!("'{w}'"),
        }
    }

    fn error<T>(&self, expected: &str) -> Result<T, ParseError> {
        Err(ParseError { position: self.pos(), message: format!("expected {expected}, found {}", self.describe()) })
    }

    fn keyword(&mut self, k: &str) -> bool {
        if let Some((Tok::Word(w), _)) = self.peek()
            && is_keyword(w, k)
        {
            self.at += 1;
            return true;
        }
        false
    }

    fn name(&mut self, what: &str) -> Result<(String, usize), ParseError> {
        match self.peek() {
            Some((Tok::Word(w), p)) if !is_any_keyword(w) => {
                let r = (w.to_string(), *p);
                self.at += 1;
                Ok(r)
            }
            _ => self.error(what),
        }
    }

    fn or(&mut self) -> Result<Expr, ParseError> {
        let mut items = vec![self.and()?];
        while self.keyword("or") {
            items.push(self.and()?);
        }
        Ok(if items.len() == 1 { items.pop().expect("one item") } else { Expr::Or(items) })
    }

    fn and(&mut self) -> Result<Expr, ParseError> {
        let mut items = vec![self.unary()?];
        while self.keyword("and") {
            items.push(self.unary()?);
        }
        Ok(if items.len() == 1 { items.pop().expect("one item") } else { Expr::And(items) })
    }

    fn unary(&mut self) -> Result<Expr, ParseError> {
        if self.keyword("not") {
            return Ok(Expr::Not(Box::new(self.unary()?)));
        }
        if let Some((Tok::Open, _)) = self.peek() {
            self.at += 1;
            let e = self.or()?;
            if let Some((Tok::Close, _)) = self.peek() {
                self.at += 1;
                return Ok(e);
            }
            return self.error("')' or 'and'/'or'");
        }
        let (variable, variable_at) = self.name("a variable name, 'not' or '('")?;
        if !self.keyword("is") {
            return self.error(&format!("'is' after '{variable}'"));
        }
        let negated = self.keyword("not");
        let (term, term_at) = self.name("a term name after 'is'")?;
        let clause = Expr::Is { variable, variable_at, term, term_at };
        Ok(if negated { Expr::Not(Box::new(clause)) } else { clause })
    }

    fn finish(&self) -> Result<(), ParseError> {
        if self.peek().is_some() { self.error("'and', 'or' or the end of the rule") } else { Ok(()) }
    }
}

/// Parses an antecedent (`if` text), e.g. `x is L and (y is N or y is not Z)`.
pub fn parse_antecedent(text: &str) -> Result<Expr, ParseError> {
    let mut p = Parser::new(text)?;
    let e = p.or()?;
    p.finish()?;
    Ok(e)
}

/// Parses a consequent (`then` text), e.g. `v is slow and w is left`.
pub fn parse_consequent(text: &str) -> Result<Vec<Assignment>, ParseError> {
    let mut p = Parser::new(text)?;
    let mut out = Vec::new();
    loop {
        let (variable, variable_at) = p.name("an output variable name")?;
        if !p.keyword("is") {
            return p.error(&format!("'is' after '{variable}'"));
        }
        if let Some((Tok::Word(w), _)) = p.peek()
            && is_keyword(w, "not")
        {
            return p.error("a term name ('not' is not allowed in a consequent)");
        }
        let (term, term_at) = p.name("a term name after 'is'")?;
        out.push(Assignment { variable, variable_at, term, term_at });
        if !p.keyword("and") {
            break;
        }
    }
    p.finish()?;
    Ok(out)
}

/// One instruction of a compiled antecedent, run on a small value stack.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Op {
    /// Push the degree of input term number `.0` (flat index over all inputs' terms).
    Load(u32),
    /// Replace the top with `1 - top`.
    Not,
    /// Replace the top `n` values with their minimum.
    And(u32),
    /// Replace the top `n` values with their maximum.
    Or(u32),
}

/// Appends the postfix program of `e` to `ops`, resolving clauses with `resolve`; returns the
/// stack depth the program needs.
pub(crate) fn compile<E>(
    e: &Expr,
    ops: &mut Vec<Op>,
    resolve: &mut impl FnMut(&Expr) -> Result<u32, E>,
) -> Result<usize, E> {
    match e {
        Expr::Is { .. } => {
            ops.push(Op::Load(resolve(e)?));
            Ok(1)
        }
        Expr::Not(inner) => {
            let d = compile(inner, ops, resolve)?;
            ops.push(Op::Not);
            Ok(d)
        }
        Expr::And(items) | Expr::Or(items) => {
            let mut depth = 0;
            for (k, item) in items.iter().enumerate() {
                depth = depth.max(k + compile(item, ops, resolve)?);
            }
            let n = items.len() as u32;
            ops.push(if matches!(e, Expr::And(_)) { Op::And(n) } else { Op::Or(n) });
            Ok(depth)
        }
    }
}

/// Runs a compiled antecedent on the input term degrees `mu`, using `stack` (capacity
/// reserved at load, so no allocation).
#[inline]
pub(crate) fn run(ops: &[Op], mu: &[f64], stack: &mut Vec<f64>) -> f64 {
    stack.clear();
    for op in ops {
        match *op {
            Op::Load(i) => stack.push(mu[i as usize]),
            Op::Not => {
                let top = stack.last_mut().expect("compiled program");
                *top = 1.0 - *top;
            }
            Op::And(n) | Op::Or(n) => {
                let from = stack.len() - n as usize;
                let mut acc = stack[from];
                let and = matches!(op, Op::And(_));
                for &v in &stack[from + 1..] {
                    acc = if and { acc.min(v) } else { acc.max(v) };
                }
                stack.truncate(from);
                stack.push(acc);
            }
        }
    }
    stack.pop().expect("compiled program leaves one value")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn is(v: &str, t: &str) -> Expr {
        // Positions are not compared by these structural tests.
        Expr::Is { variable: v.into(), variable_at: 0, term: t.into(), term_at: 0 }
    }

    fn strip(e: Expr) -> Expr {
        match e {
            Expr::Is { variable, term, .. } => is(&variable, &term),
            Expr::Not(i) => Expr::Not(Box::new(strip(*i))),
            Expr::And(v) => Expr::And(v.into_iter().map(strip).collect()),
            Expr::Or(v) => Expr::Or(v.into_iter().map(strip).collect()),
        }
    }

    #[test]
    fn and_binds_tighter_than_or() {
        let e = strip(parse_antecedent("x is L or x is M and y is N").unwrap());
        assert_eq!(e, Expr::Or(vec![is("x", "L"), Expr::And(vec![is("x", "M"), is("y", "N")])]));
    }

    #[test]
    fn parentheses_not_and_is_not_nest() {
        let e = strip(parse_antecedent("NOT (x is L AND (y is N or y is not Z))").unwrap());
        let inner = Expr::And(vec![is("x", "L"), Expr::Or(vec![is("y", "N"), Expr::Not(Box::new(is("y", "Z")))])]);
        assert_eq!(e, Expr::Not(Box::new(inner)));
    }

    #[test]
    fn errors_carry_the_position() {
        let e = parse_antecedent("x is L and (y is N").unwrap_err();
        assert_eq!(e.position, 18);
        assert!(e.message.contains("')'"), "{}", e.message);
        let e = parse_antecedent("x L").unwrap_err();
        assert_eq!(e.position, 2);
        let e = parse_antecedent("x is L y is N").unwrap_err();
        assert_eq!(e.position, 7);
        let e = parse_antecedent("x is L & y is N").unwrap_err();
        assert_eq!(e.position, 7);
        let e = parse_antecedent("").unwrap_err();
        assert_eq!(e.position, 0);
        let e = parse_consequent("z is not lo").unwrap_err();
        assert_eq!(e.position, 5);
    }

    #[test]
    fn consequents_list_assignments() {
        let a = parse_consequent("v is slow and w is left").unwrap();
        assert_eq!(a.len(), 2);
        assert_eq!((a[1].variable.as_str(), a[1].term.as_str(), a[1].term_at), ("w", "left", 19));
    }

    #[test]
    fn compiled_program_computes_min_max_and_complement() {
        let e = parse_antecedent("a is t and (b is t or not c is t)").unwrap();
        let mut ops = Vec::new();
        let depth = compile(&e, &mut ops, &mut |c: &Expr| -> Result<u32, ()> {
            let Expr::Is { variable, .. } = c else { unreachable!() };
            Ok(match variable.as_str() {
                "a" => 0,
                "b" => 1,
                _ => 2,
            })
        })
        .unwrap();
        let mut stack = Vec::with_capacity(depth);
        // min(0.7, max(0.2, 1 - 0.6)) = 0.4
        let v = run(&ops, &[0.7, 0.2, 0.6], &mut stack);
        assert!((v - 0.4).abs() < 1e-15);
        assert!(stack.capacity() >= depth);
    }
}
