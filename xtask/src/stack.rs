//! Worst stack depth of the firmware image by static analysis of its call
//! graph, for `cargo xtask size`.
//!
//! The image is disassembled with `llvm-objdump -d`; each function's frame
//! is what its prologue takes (`push`/`push.w` registers × 4 B, `vpush`
//! double registers × 8 B, `sub sp, #n`), its callees are the targets of
//! its `bl` and of `b`/`b.w` to another function's start (tail calls). The
//! depth of a function is its frame plus its deepest callee's depth.
//! The worst depth of the firmware is the depth of `Reset` (which reaches
//! the executor), plus the main task's poll function (called by the
//! executor through a function pointer, which the graph cannot follow),
//! plus the deepest interrupt handler with its exception frame (104 B:
//! 8 words and the lazily stacked FPU context, one level of nesting).
//!
//! Every function's own frame is listed too ([`Report::frames`]): `cargo
//! xtask size` fails when a frame other than a root's is at or above the
//! MPU guard ([`frames_over`]), since such a frame can step over it.
//!
//! Limits: other indirect calls (`blx rN`: wakers, vtables) are counted
//! as zero and reported; recursion is cut at the first repeat and
//! reported; a frame that moves `sp` by a register (alloca) is not seen.
//! What the analysis cannot bound is measured on the board: the painted
//! stack's high-water mark (object 0x200B sub 3).

use std::collections::BTreeMap;

/// Exception entry with the FPU context (Cortex-M4F, lazy stacking) [B].
const EXCEPTION_FRAME: u64 = 104;

/// One function of the image.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Func {
    /// Demangled name.
    pub name: String,
    /// Bytes its prologue takes.
    pub frame: u64,
    /// Start addresses of the functions it calls.
    pub calls: Vec<u64>,
    /// It calls through a register.
    pub indirect: bool,
}

/// The functions of a disassembly, by start address.
pub fn parse(disasm: &str) -> BTreeMap<u64, Func> {
    let mut funcs: BTreeMap<u64, Func> = BTreeMap::new();
    let mut cur: Option<u64> = None;
    let mut branches: Vec<(u64, u64)> = Vec::new();
    for line in disasm.lines() {
        if let Some((addr, name)) = header(line) {
            if !name.starts_with('$') {
                funcs.insert(
                    addr,
                    Func {
                        name: name.to_string(),
                        ..Func::default()
                    },
                );
                cur = Some(addr);
            }
            continue;
        }
        let (Some(at), Some((op, args))) = (cur, instruction(line)) else {
            continue;
        };
        let Some(f) = funcs.get_mut(&at) else {
            continue;
        };
        match op {
            "push" | "push.w" => f.frame += 4 * register_count(args),
            "vpush" | "vpush.64" => f.frame += 8 * register_count(args),
            "sub" | "sub.w" | "subw" if args.starts_with("sp,") => f.frame += immediate(args),
            "bl" => f.calls.extend(target(args)),
            "blx" => f.indirect = true,
            "b" | "b.w" => branches.extend(target(args).map(|t| (at, t))),
            _ => {}
        }
    }
    // A branch to another function's start is a tail call.
    for (from, to) in branches {
        if from != to && funcs.contains_key(&to) {
            if let Some(f) = funcs.get_mut(&from) {
                f.calls.push(to);
            }
        }
    }
    funcs
}

/// `08000b08 <name>:` → (address, name).
fn header(line: &str) -> Option<(u64, &str)> {
    let (addr, rest) = line.split_once(' ')?;
    let name = rest.strip_prefix('<')?.strip_suffix(">:")?;
    Some((u64::from_str_radix(addr, 16).ok()?, name))
}

/// ` 8000b08:  \tpush\t{r4, lr}` → ("push", "{r4, lr}").
fn instruction(line: &str) -> Option<(&str, &str)> {
    let (_, rest) = line.trim_start().split_once(':')?;
    let mut parts = rest.trim().splitn(2, char::is_whitespace);
    let op = parts.next()?;
    Some((op, parts.next().unwrap_or("").trim()))
}

/// Registers in `{r4, r5, lr}` or `{d8, d9}` (ranges `r4-r7` counted too).
fn register_count(args: &str) -> u64 {
    let list = args.split('}').next().unwrap_or("").trim_start_matches('{');
    list.split(',')
        .map(str::trim)
        .filter(|r| !r.is_empty())
        .map(|r| match r.split_once('-') {
            Some((a, b)) => {
                let n = |s: &str| s.trim_start_matches(char::is_alphabetic).parse::<u64>();
                match (n(a), n(b)) {
                    (Ok(a), Ok(b)) if b >= a => b - a + 1,
                    _ => 1,
                }
            }
            None => 1,
        })
        .sum()
}

/// The immediate of `sp, sp, #0x6300` / `sp, #24` (0 for a register).
fn immediate(args: &str) -> u64 {
    let Some(imm) = args.split('#').nth(1) else {
        return 0;
    };
    let imm = imm.split_whitespace().next().unwrap_or("");
    match imm.strip_prefix("0x") {
        Some(hex) => u64::from_str_radix(hex, 16).unwrap_or(0),
        None => imm.parse().unwrap_or(0),
    }
}

/// The address of `0x80094d0 <name> @ imm = #…`.
fn target(args: &str) -> Option<u64> {
    let hex = args.split_whitespace().next()?.strip_prefix("0x")?;
    u64::from_str_radix(hex, 16).ok()
}

/// A depth and how it was reached.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Depth {
    /// Bytes.
    pub bytes: u64,
    /// The deepest path, outermost first.
    pub path: Vec<String>,
    /// An indirect call or a recursion lies on the way (the depth is then
    /// a lower bound).
    pub partial: bool,
}

/// The depth of the function at `addr` (memoised; recursion cut).
pub fn depth(funcs: &BTreeMap<u64, Func>, addr: u64, memo: &mut BTreeMap<u64, Depth>) -> Depth {
    if let Some(d) = memo.get(&addr) {
        return d.clone();
    }
    let Some(f) = funcs.get(&addr) else {
        return Depth::default();
    };
    // Marks `addr` as in progress: a call back to it is a recursion.
    memo.insert(
        addr,
        Depth {
            partial: true,
            ..Depth::default()
        },
    );
    let mut worst = Depth::default();
    let mut partial = f.indirect;
    for &c in &f.calls {
        let d = depth(funcs, c, memo);
        partial |= d.partial;
        if d.bytes > worst.bytes || worst.path.is_empty() {
            worst = d;
        }
    }
    worst.bytes += f.frame;
    worst.path.insert(0, f.name.clone());
    worst.partial = partial;
    memo.insert(addr, worst.clone());
    worst
}

/// The firmware's worst depth: thread mode (`Reset` and the main task) and
/// the deepest interrupt handler.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Report {
    /// `Reset` down to the executor and the main task.
    pub thread: Depth,
    /// The deepest interrupt or exception handler, exception frame
    /// included.
    pub handler: Depth,
    /// Every function's own frame, largest first: (name, bytes, root). A
    /// root (`Reset`, the main task's poll function) is entered at a
    /// fixed depth near the top of the stack, never near the guard.
    pub frames: Vec<(String, u64, bool)>,
}

/// Whether `name` is a thread-mode root: entered once, at the top of the
/// stack (cortex-m-rt's `Reset`, embassy's main task poll function).
pub fn is_root(name: &str) -> bool {
    name == "Reset"
        || name == "__stext"
        || (name.contains("____embassy_main_task") && name.contains("closure"))
}

/// A function's name and its frame [B].
pub type Frame = (String, u64);

/// The frames at or above `guard` bytes: a frame that large can step over
/// an MPU guard of that size (its writes land below the guard without
/// touching it). Roots are listed apart (second): they sit at the top of
/// the stack.
pub fn frames_over(r: &Report, guard: u64) -> (Vec<Frame>, Vec<Frame>) {
    let over = r.frames.iter().filter(|f| f.1 >= guard);
    let (roots, others): (Vec<_>, Vec<_>) = over.partition(|f| f.2);
    let strip = |v: Vec<&(String, u64, bool)>| v.into_iter().map(|f| (f.0.clone(), f.1)).collect();
    (strip(others), strip(roots))
}

impl Report {
    /// Thread plus one handler [B].
    pub fn total(&self) -> u64 {
        self.thread.bytes + self.handler.bytes
    }
}

/// Handlers: the vector table's entries other than `Reset`.
fn is_handler(name: &str) -> bool {
    name.ends_with("_IRQHandler")
        || matches!(
            name,
            "NonMaskableInt"
                | "HardFault"
                | "MemoryManagement"
                | "BusFault"
                | "UsageFault"
                | "SVCall"
                | "PendSV"
                | "SysTick"
                | "DefaultHandler"
        )
        || name.starts_with("FDCAN")
        || name.starts_with("DMA1_")
        || name.starts_with("TIM")
}

/// Analyses a disassembly (see the module docs).
///
/// # Errors
/// When it has no `Reset` or no main task.
pub fn analyse(disasm: &str) -> Result<Report, String> {
    let funcs = parse(disasm);
    let find =
        |pred: &dyn Fn(&str) -> bool| funcs.iter().find(|(_, f)| pred(&f.name)).map(|(a, _)| *a);
    // cortex-m-rt's `Reset` starts `.text`: objdump may name it `__stext`.
    let reset = find(&|n| n == "Reset" || n == "__stext").ok_or("no `Reset` in the disassembly")?;
    let task = find(&|n| n.contains("____embassy_main_task") && n.contains("closure"))
        .ok_or("no embassy main task in the disassembly")?;
    let mut memo = BTreeMap::new();
    let mut thread = depth(&funcs, reset, &mut memo);
    let t = depth(&funcs, task, &mut memo);
    thread.bytes += t.bytes;
    thread.partial |= t.partial;
    thread.path.extend(t.path);
    let mut handler = Depth::default();
    for (&a, f) in &funcs {
        if is_handler(&f.name) {
            let d = depth(&funcs, a, &mut memo);
            if d.bytes > handler.bytes {
                handler = d;
            }
        }
    }
    handler.bytes += EXCEPTION_FRAME;
    let mut frames: Vec<(String, u64, bool)> = funcs
        .values()
        .filter(|f| f.frame > 0)
        .map(|f| (f.name.clone(), f.frame, is_root(&f.name)))
        .collect();
    frames.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    Ok(Report {
        thread,
        handler,
        frames,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    const DISASM: &str = "\
08000100 <Reset>:
 8000100:      \tpush\t{r7, lr}
 8000102:      \tbl\t0x8000200 <main> @ imm = #252
08000200 <main>:
 8000200:      \tpush\t{r4, r5, r6, r7, lr}
 8000202:      \tsub.w\tsp, sp, #0x100
 8000206:      \tblx\tr3
 8000208:      \tb.w\t0x8000300 <leaf> @ imm = #244
08000300 <leaf>:
 8000300:      \tvpush\t{d8, d9, d10, d11, d12, d13, d14, d15}
 8000304:      \tsub\tsp, #24
08000400 <perpend_fw::____embassy_main_task::inner::{{closure}}>:
 8000400:      \tpush.w\t{r4-r11, lr}
 8000404:      \tbl\t0x8000400 <perpend_fw::____embassy_main_task::inner::{{closure}}>
08000500 <FDCAN1_IT0>:
 8000500:      \tpush\t{r7, lr}
 8000502:      \tbl\t0x8000300 <leaf> @ imm = #-516
";

    #[test]
    fn frames_calls_and_tail_calls() {
        let f = parse(DISASM);
        assert_eq!(f[&0x800_0100].frame, 8);
        assert_eq!(f[&0x800_0200].frame, 20 + 0x100);
        assert_eq!(f[&0x800_0200].calls, vec![0x800_0300]);
        assert!(f[&0x800_0200].indirect);
        assert_eq!(f[&0x800_0300].frame, 64 + 24);
        assert_eq!(f[&0x800_0400].frame, 36);
    }

    #[test]
    fn worst_path_with_task_and_handler() {
        let r = analyse(DISASM).unwrap();
        assert_eq!(r.thread.bytes, 8 + 276 + 88 + 36);
        assert!(r.thread.partial, "the indirect call and the recursion");
        assert_eq!(r.thread.path[..3], ["Reset", "main", "leaf"]);
        assert_eq!(r.handler.bytes, 8 + 88 + EXCEPTION_FRAME);
        assert_eq!(r.total(), r.thread.bytes + r.handler.bytes);
        assert_eq!(r.frames[0], ("main".to_string(), 276, false));
        let (over, roots) = frames_over(&r, 64);
        assert_eq!(
            over,
            [("main".to_string(), 276), ("leaf".to_string(), 88)],
            "frames at or above the guard"
        );
        assert!(roots.is_empty());
        let (over, roots) = frames_over(&r, 30);
        assert!(over.iter().all(|f| f.1 >= 30));
        assert_eq!(roots.len(), 1, "the main task's poll function: {roots:?}");
    }
}
