"""Read U(C)RDF files into :class:`ucrdf.model.Robot`.

Three passes, each reporting ``path:line: message`` diagnostics: XML syntax (lxml), structure (the
XSD shipped in the package, ``ucrdf.xsd``), then the document-level rules the schema cannot express
(duplicates, counts, indices) followed by the semantic checks of :mod:`ucrdf.checks`. All problems
of a pass are collected before raising one :class:`ucrdf.errors.UcrdfError`.
"""

from __future__ import annotations

import copy
import math
import re
from functools import lru_cache
from importlib import resources
from pathlib import Path

from lxml import etree

from ucrdf.checks import LineKey, LineTable
from ucrdf.checks import check as semantic_check
from ucrdf.errors import Diagnostic, UcrdfError
from ucrdf.model import (
    Actuation,
    Backbone,
    Bendable,
    ControlJoint,
    CurvatureLimits,
    Geometry,
    Inertial,
    Interface,
    Joint,
    JointLimit,
    Link,
    ModelSpec,
    Origin,
    PwmPulse,
    Robot,
    Ros2Control,
    Servo,
    Vec3,
)
from ucrdf.numtext import MAX_WHOLE_DIGITS, number, shown, whole

# Joint children stored verbatim in Joint.extensions (valid URDF we do not interpret).
_JOINT_OPAQUE = ("calibration", "dynamics", "mimic", "safety_controller")
# The interface params read as numbers; the others pass through as the text written
_NUMERIC_INTERFACE_PARAMS = ("initial_value", "min", "max")


@lru_cache(maxsize=1)
def schema() -> etree.XMLSchema:
    """The U(C)RDF XML Schema shipped as package data (compiled once)."""
    data = resources.files("ucrdf").joinpath("ucrdf.xsd").read_bytes()
    return etree.XMLSchema(etree.fromstring(data))


#: Largest file :func:`read_file` reads, in bytes. A robot description is kilobytes (meshes are
#: files of their own); a bigger file is the wrong one, and /dev/zero must not fill the memory.
MAX_FILE_BYTES = 64 * 1024 * 1024


def load(path: str | Path, *, check: bool = True) -> Robot:
    """Parse and (by default) semantically check the U(C)RDF file at ``path``.

    Raises UcrdfError with one diagnostic per problem; a missing or unreadable file is one
    diagnostic too, so callers need to handle only that one exception type.
    """
    return parse_bytes(read_file(path), source=str(path), check=check)


def read_file(path: str | Path) -> bytes:
    """The bytes of the file at ``path``, at most :data:`MAX_FILE_BYTES` of them; UcrdfError with
    one diagnostic when it cannot be read, is larger, or ``path`` is empty."""
    source = str(path)
    if not source:  # Path("") is the current directory: "Is a directory" would mislead
        raise UcrdfError([Diagnostic("''", 0, "cannot read file: the path is empty")])
    try:
        with open(path, "rb") as file:
            data = file.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise UcrdfError([Diagnostic(source, 0, f"cannot read file: {reason}")]) from None
    if len(data) > MAX_FILE_BYTES:
        message = f"file is larger than {MAX_FILE_BYTES >> 20} MiB: not a robot description"
        raise UcrdfError([Diagnostic(source, 0, message)])
    return data


# the encoding="…" of an XML declaration at the start of a text
_ENCODING_DECLARATION = re.compile(r"""\A(\ufeff?<\?xml\s[^>]*?)\s+encoding\s*=\s*(["'])[^"']*\2""")


def parse_string(text: str, source: str = "<string>", *, check: bool = True) -> Robot:
    """Parse U(C)RDF from a string; ``source`` names it in diagnostics.

    The text is already decoded: an ``encoding="…"`` in its XML declaration names what the bytes
    once were and is dropped (it would make the parser decode the text a second time)."""
    text = _ENCODING_DECLARATION.sub(r"\1", text, count=1)
    # a lone surrogate is not text: it reaches the XML parser as invalid UTF-8, a syntax error
    return parse_bytes(text.encode("utf-8", "surrogatepass"), source=source, check=check)


def parse_bytes(data: bytes, source: str = "<bytes>", *, check: bool = True) -> Robot:
    """Parse U(C)RDF from bytes (any encoding the XML declaration names)."""
    robot, lines, diagnostics = _build(data, source)
    if check:
        diagnostics += semantic_check(robot, lines)
    if diagnostics:
        raise UcrdfError(diagnostics)
    return robot


def parse_with_lines(data: bytes, source: str = "<bytes>") -> tuple[Robot, LineTable]:
    """Parse without semantic checks, also returning the line table (for tools that run
    :func:`ucrdf.checks.check` themselves and want precise lines)."""
    robot, lines, diagnostics = _build(data, source)
    if diagnostics:
        raise UcrdfError(diagnostics)
    return robot, lines


def _build(data: bytes, source: str) -> tuple[Robot, LineTable, list[Diagnostic]]:
    """Syntax and schema errors raise at once (nothing to build on); document-level problems are
    returned so the semantic checks can add theirs to the same report."""
    root, log = _parse_xml(data, source)
    _refuse_dtd(root, data, source, log)
    if root.tag != "robot":
        line = root.sourceline or 0
        raise UcrdfError(
            [Diagnostic(source, line, f"root element is <{root.tag}>, expected <robot>")]
        )
    _refuse_xacro(root, source)
    xsd = schema()
    try:
        valid = xsd.validate(root)
    except etree.XMLSchemaValidateError as exc:  # libxml2 internal failure: still no traceback
        line = root.sourceline or 0
        raise UcrdfError([Diagnostic(source, line, f"schema validation failed: {exc}")]) from None
    if not valid:
        raise UcrdfError(
            Diagnostic(source, err.line, _clean_schema_message(err.message))
            for err in xsd.error_log
        )
    builder = _Builder(source)
    robot = builder.build(root)
    return robot, builder.lines, list(builder.diagnostics)


#: Namespace URIs xacro files declare (``xmlns:xacro="…"``).
XACRO_NAMESPACES = frozenset(
    {"http://www.ros.org/wiki/xacro", "http://ros.org/wiki/xacro", "http://wiki.ros.org/xacro"}
)
# ${expression} and $(substitution arg) are xacro syntax, never U(C)RDF text
_XACRO_SUBSTITUTION = re.compile(r"\$[{(]")


def _refuse_xacro(root: etree._Element, source: str) -> None:
    """A file that still holds xacro (``<xacro:include>``, ``<xacro:macro>``, macro calls,
    ``${…}``/``$(…)`` substitutions) is not an expanded robot: one diagnostic per element, at its
    line. The bare ``xmlns:xacro`` declaration is tolerated (the paper's Listing 1 has it)."""
    found: list[Diagnostic] = []
    hint = "expand it first: xacro FILE > robot.ucrdf"
    for el in root.iter():
        if not isinstance(el.tag, str):
            continue
        qname = etree.QName(el)
        if qname.namespace in XACRO_NAMESPACES or el.prefix == "xacro":
            found.append(
                Diagnostic(
                    source,
                    el.sourceline or 0,
                    f"xacro element <xacro:{qname.localname}>: this file is unexpanded xacro, "
                    f"not a U(C)RDF robot; {hint}",
                )
            )
            continue
        texts = [(f"attribute {k}", v) for k, v in el.attrib.items()]
        texts.append(("text", el.text or ""))
        for what, value in texts:
            if _XACRO_SUBSTITUTION.search(value):
                found.append(
                    Diagnostic(
                        source,
                        el.sourceline or 0,
                        f"xacro substitution in <{qname.localname}> {what} {value.strip()!r}: "
                        f"this file is unexpanded xacro; {hint}",
                    )
                )
                break
    if found:
        raise UcrdfError(found)


# the pieces of a prolog and of an internal DTD subset, in a document libxml2 has parsed (so
# well-formed): white space, processing instructions, comments, a DOCTYPE up to its subset, and
# the declarations in the subset (with their kind and name)
_PROLOG = re.compile(r"\s+|<\?.*?\?>|<!--.*?-->", re.DOTALL)
_DOCTYPE = re.compile(r"""<!DOCTYPE\s(?:[^\[>"']|"[^"]*"|'[^']*')*""")
_SUBSET = re.compile(
    r"""\s+|<\?.*?\?>|<!--.*?-->|%[^;]*;"""
    r"""|<!(?P<kind>[A-Z]+)\s+(?:%\s+)?(?P<name>[^\s>]+)(?:[^"'>]|"[^"]*"|'[^']*')*>""",
    re.DOTALL,
)


def _doctype(text: str) -> tuple[int, list[re.Match[str]]]:
    """Offset of the ``<!DOCTYPE`` of ``text`` (-1: none) and the declarations of its internal
    subset, in order."""
    pos = 1 if text.startswith("\ufeff") else 0
    while (m := _PROLOG.match(text, pos)) is not None:
        pos = m.end()
    head = _DOCTYPE.match(text, pos)
    if head is None:
        return -1, []
    declarations = []
    if text.startswith("[", head.end()):
        pos = head.end() + 1
        while (m := _SUBSET.match(text, pos)) is not None:
            if m.group("kind"):
                declarations.append(m)
            pos = m.end()
    return head.start(), declarations


def _refuse_dtd(root: etree._Element, data: bytes, source: str, log: etree._ListErrorLog) -> None:
    """A ``<!DOCTYPE>`` may name the root element and nothing more. An external DTD (``SYSTEM``
    or ``PUBLIC``), entity declarations, the other declarations of an internal subset
    (``<!ATTLIST>`` defaults, ``<!ELEMENT>``, ``<!NOTATION>``) and references to entities nothing
    defines are refused, each at its line: nothing is read or expanded (a description must not
    pull in files, and text hidden behind an entity or a default hides what the robot is), and
    nothing is silently dropped (libxml2 leaves an undefined entity out of an attribute)."""
    docinfo = root.getroottree().docinfo
    dtd = docinfo.internalDTD
    undefined = [e for e in log if e.type == etree.ErrorTypes.WAR_UNDECLARED_ENTITY]
    if dtd is None and not undefined:
        return
    try:  # the text, for the lines of the declarations
        text = data.decode(docinfo.encoding or "utf-8", "replace")
    except LookupError:  # an encoding libxml2 knows and Python does not
        text = data.decode("utf-8", "replace")
    start, declarations = _doctype(text)

    def line(offset: int) -> int:
        return text.count("\n", 0, offset) + 1 if offset >= 0 else 1

    found = []
    if docinfo.system_url is not None or docinfo.public_id is not None:
        names = " ".join(repr(n) for n in (docinfo.public_id, docinfo.system_url) if n)
        found.append(
            Diagnostic(
                source,
                line(start),
                f"external DTD {names}: never read; a U(C)RDF file has no DTD (remove it from "
                "the <!DOCTYPE>)",
            )
        )
    entities = {e.name: e for e in dtd.iterentities()} if dtd is not None else {}
    hint = (
        "write the text in place (the predefined entities such as &amp; and character "
        "references work)"
    )
    for m in declarations:
        kind, name = m.group("kind", "name")
        if kind == "ENTITY":
            entity = entities.pop(name, None)
            url = entity.system_url if entity is not None else None
            what = f"external entity {name!r} ({url}): never read" if url else f"entity {name!r}"
            message = f"DTD entity declarations are not supported in U(C)RDF ({what}); {hint}"
        elif kind == "ATTLIST":
            message = (
                f"DTD declaration <!ATTLIST {name} …> is not supported in U(C)RDF: its defaults "
                "are never applied; write the attributes in the elements"
            )
        else:
            message = (
                f"DTD declaration <!{kind} {name} …> is not supported in U(C)RDF (ucrdf.xsd "
                "defines the structure); remove it"
            )
        found.append(Diagnostic(source, line(m.start()), message))
    for name in entities:  # declared in a way the scan above did not see: still refused
        message = f"DTD entity declarations are not supported in U(C)RDF (entity {name!r}); {hint}"
        found.append(Diagnostic(source, line(start), message))
    for entry in undefined:
        name = re.search(r"'([^']*)'", entry.message)
        found.append(
            Diagnostic(
                source,
                entry.line,
                f"entity {name.group(1) if name else '?'!r} is not defined: U(C)RDF never "
                f"expands entities; {hint}",
            )
        )
    if found:
        raise UcrdfError(found)


def _parse_xml(data: bytes, source: str) -> tuple[etree._Element, etree._ListErrorLog]:
    """The root element and the parser's log (its warnings name undefined entities)."""
    # entities are never expanded: a document declaring or using any is refused after parsing
    # (_refuse_dtd), so a description never reads files or the network
    parser = etree.XMLParser(
        resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False
    )
    try:
        root = etree.fromstring(data, parser)
    except etree.XMLSyntaxError as exc:
        # the parser's own log (exc.error_log may hold errors of earlier documents)
        entries = [e for e in parser.error_log if e.level >= etree.ErrorLevels.ERROR]
        if entries:
            first = entries[0]
            diagnostic = Diagnostic(source, first.line, f"XML syntax error: {first.message}")
        else:
            message = re.sub(r", line \d+, column \d+$", "", exc.msg or "not well-formed")
            diagnostic = Diagnostic(source, exc.lineno or 0, f"XML syntax error: {message}")
        raise UcrdfError([diagnostic]) from None
    if root is None:
        raise UcrdfError([Diagnostic(source, 0, "empty document")])
    return root, parser.error_log


# libxml2's schema messages quote names and values in '…' (e.g. "Element 'backbone', attribute
# 'length': '0.3m' is not a valid value of the atomic type 'xs:double'"): the pieces between
# quotes alternate outside / inside, and a long inside piece (a 5000-digit value) is cut
_LONG_QUOTED = 24


def _clean_schema_message(message: str) -> str:
    """libxml2's schema messages, minus the noise of namespace braces and trailing dots."""
    message = message.replace("{http://www.w3.org/2001/XMLSchema}", "xs:").rstrip(".")
    pieces = message.split("'")
    if len(pieces) % 2 == 0:  # an odd number of quotes: no telling the values apart
        return message
    return "".join(
        piece if k % 2 == 0 else shown(piece, _LONG_QUOTED) if len(piece) > _LONG_QUOTED
        else f"'{piece}'"
        for k, piece in enumerate(pieces)
    )  # fmt: skip


def normalise_xml(element: etree._Element) -> str:
    """Canonical text of an element kept verbatim (visual, collision, extensions): exclusive C14N
    with comments and whitespace-only text removed, so a parse -> write -> parse compares equal."""
    el = copy.deepcopy(element)
    el.tail = None
    for node in list(el.iter()):
        if not isinstance(node.tag, str):  # comment or processing instruction
            parent = node.getparent()
            if parent is not None:
                _remove_keep_tail(node)
            continue
        if node.text is not None and not node.text.strip():
            node.text = None
        if node is not el and node.tail is not None and not node.tail.strip():
            node.tail = None
    return etree.tostring(el, method="c14n", exclusive=True, with_comments=False).decode("utf-8")


def _remove_keep_tail(node: etree._Element) -> None:
    parent = node.getparent()
    tail = node.tail
    if tail and tail.strip():
        prev = node.getprevious()
        if prev is not None:
            prev.tail = (prev.tail or "") + tail
        else:
            parent.text = (parent.text or "") + tail
    parent.remove(node)


def _children(element: etree._Element) -> list[etree._Element]:
    """Element children only (comments and processing instructions skipped)."""
    return [c for c in element if isinstance(c.tag, str)]


def _float(text: str) -> float:
    """``xs:double`` text as a float; ValueError for anything else (``1_5``, ``infinity``: what
    Python reads but a C++ reader of the file does not)."""
    value = number(text)
    if value is None:
        raise ValueError(f"not a number: {shown(text)}")
    return value


def _number_or_text(text: str) -> float | str:
    """Parameter values: a float when the text is ``xs:double`` text, else the stripped text (for
    whoever needs a number to report)."""
    stripped = text.strip()
    value = number(stripped)
    return stripped if value is None else value


def _vec3(text: str | None, default: Vec3) -> Vec3:
    if text is None:
        return default
    x, y, z = (_float(v) for v in text.split())
    return (x, y, z)


class _Builder:
    """Turns a schema-valid tree into a Robot, recording lines and document-level problems."""

    def __init__(self, source: str):
        self.source = source
        self.diagnostics: list[Diagnostic] = []
        self.lines: LineTable = {}

    def dropped(self, kind: str, name: str, parent: str | None, child: str | None) -> None:
        """Record a joint/bendable left out of the Robot because it was reported invalid, so the
        semantic checks do not report its absence again (a second root link, a ros2_control
        joint naming nothing): ``("invalid", kind, name, parent, child)`` in the line table."""
        self.lines[("invalid", kind, name, parent, child)] = 0

    def error(self, element: etree._Element | int, message: str) -> None:
        line = element if isinstance(element, int) else (element.sourceline or 0)
        self.diagnostics.append(Diagnostic(self.source, line, message))

    def whole(
        self, element: etree._Element, attr: str, owner: str, default: str = ""
    ) -> int | None:
        """The whole-number attribute ``attr`` of ``element`` (``default`` when absent); None,
        reported at the element's line, when it has more than MAX_WHOLE_DIGITS digits (the
        schema has checked the rest of its syntax)."""
        text = element.get(attr, default)
        value = whole(text)
        if value is None:
            self.error(
                element,
                f"{owner} <{element.tag} {attr}={shown(text)}> is out of range: a whole number "
                f"has at most {MAX_WHOLE_DIGITS} digits here",
            )
        return value

    # -- robot ---------------------------------------------------------------------------------
    def build(self, root: etree._Element) -> Robot:
        robot = Robot(name=root.get("name", ""), source=self.source)
        self.lines[("robot",)] = root.sourceline or 0
        seen_kinematic: dict[str, tuple[str, int]] = {}  # joint/bendable name -> (kind, line)
        for child in _children(root):
            tag = child.tag
            if tag == "link":
                link = self.link(child)
                if link.name in robot.links:
                    self.error(
                        child,
                        f"duplicate link name {link.name!r} "
                        f"(first defined on line {robot.links[link.name].line})",
                    )
                    continue
                robot.links[link.name] = link
            elif tag in ("joint", "bendable"):
                item = self.joint(child) if tag == "joint" else self.bendable(child)
                if item is None:
                    continue
                if item.name in seen_kinematic:
                    self.dropped(tag, item.name, item.parent, item.child)
                    kind, line = seen_kinematic[item.name]
                    self.error(
                        child,
                        f"duplicate name {item.name!r}: this {tag} has the same name as the "
                        f"{kind} on line {line} (joints and bendables share one namespace)",
                    )
                    continue
                seen_kinematic[item.name] = (tag, item.line)
                if tag == "joint":
                    robot.joints[item.name] = item
                else:
                    robot.bendables[item.name] = item
            elif tag == "ros2_control":
                robot.ros2_control.append(self.ros2_control(child, len(robot.ros2_control)))
            else:
                robot.extensions.append(normalise_xml(child))
        return robot

    # -- URDF pieces ---------------------------------------------------------------------------
    def origin(self, element: etree._Element | None) -> Origin:
        if element is None:
            return Origin()
        return Origin(
            xyz=_vec3(element.get("xyz"), (0.0, 0.0, 0.0)),
            rpy=_vec3(element.get("rpy"), (0.0, 0.0, 0.0)),
        )

    def inertial(self, element: etree._Element, key: LineKey) -> Inertial:
        origin_el = element.find("origin")
        if origin_el is not None:
            self.lines[(*key, "origin")] = origin_el.sourceline or 0
        mass_el = element.find("mass")
        inertia_el = element.find("inertia")
        inertia = (0.0,) * 6
        if inertia_el is not None:
            inertia = tuple(
                _float(inertia_el.get(k, "0")) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
            )
        return Inertial(
            mass=_float(mass_el.get("value")),
            origin=self.origin(origin_el),
            inertia=inertia,  # type: ignore[arg-type]
        )

    def link(self, element: etree._Element) -> Link:
        name = element.get("name")
        link = Link(name=name, line=element.sourceline or 0)
        self.lines[("link", name)] = link.line
        for child in _children(element):
            if child.tag == "inertial":
                if link.inertial is not None:
                    self.error(child, f"link {name!r} has more than one <inertial>")
                    continue
                link.inertial = self.inertial(child, ("link", name, "inertial"))
                self.lines[("link", name, "inertial")] = child.sourceline or 0
            elif child.tag in ("visual", "collision"):
                link.geometry.append(
                    Geometry(kind=child.tag, xml=normalise_xml(child), line=child.sourceline or 0)
                )
            else:
                link.extensions.append(normalise_xml(child))
        return link

    def _once(self, element: etree._Element, tag: str, owner: str) -> etree._Element | None:
        """The single child ``tag`` of ``element``; reports duplicates (and returns the first)."""
        found = element.findall(tag)
        for extra in found[1:]:
            self.error(extra, f"{owner} has more than one <{tag}>")
        return found[0] if found else None

    def joint(self, element: etree._Element) -> Joint | None:
        name = element.get("name")
        owner = f"joint {name!r}"
        line = element.sourceline or 0
        self.lines[("joint", name)] = line
        parent = self._once(element, "parent", owner)
        child = self._once(element, "child", owner)
        ok = True
        for tag, el in (("parent", parent), ("child", child)):
            if el is None:
                self.error(element, f"{owner} has no <{tag} link=…>")
                ok = False
            else:
                self.lines[("joint", name, tag)] = el.sourceline or 0
        origin = self._once(element, "origin", owner)
        axis = self._once(element, "axis", owner)
        limit_el = self._once(element, "limit", owner)
        if not ok:
            self.dropped(
                "joint",
                name,
                parent.get("link") if parent is not None else None,
                child.get("link") if child is not None else None,
            )
            return None
        limit = None
        if limit_el is not None:
            limit = JointLimit(
                lower=_float(limit_el.get("lower", "0")),
                upper=_float(limit_el.get("upper", "0")),
                effort=_float(limit_el.get("effort")),
                velocity=_float(limit_el.get("velocity")),
            )
            self.lines[("joint", name, "limit")] = limit_el.sourceline or 0
        if axis is not None:
            self.lines[("joint", name, "axis")] = axis.sourceline or 0
        if origin is not None:
            self.lines[("joint", name, "origin")] = origin.sourceline or 0
        extensions = [
            normalise_xml(c)
            for c in _children(element)
            if c.tag not in ("parent", "child", "origin", "axis", "limit")
        ]
        return Joint(
            name=name,
            type=element.get("type"),
            parent=parent.get("link"),
            child=child.get("link"),
            origin=self.origin(origin),
            axis=_vec3(axis.get("xyz") if axis is not None else None, (1.0, 0.0, 0.0)),
            limit=limit,
            line=line,
            extensions=extensions,
        )

    # -- bendable ------------------------------------------------------------------------------
    def bendable(self, element: etree._Element) -> Bendable | None:
        name = element.get("name")
        line = element.sourceline or 0
        key = ("bendable", name)
        self.lines[key] = line
        parent = element.find("parent")
        child = element.find("child")
        self.lines[(*key, "parent")] = parent.sourceline or 0
        self.lines[(*key, "child")] = child.sourceline or 0
        model = self.model(element.find("curvature/model"), name)
        if model is None:
            self.dropped("bendable", name, parent.get("link"), child.get("link"))
            return None
        inertial_el = element.find("inertial")
        inertial = None
        if inertial_el is not None:
            inertial = self.inertial(inertial_el, (*key, "inertial"))
            self.lines[(*key, "inertial")] = inertial_el.sourceline or 0
        origin_el = element.find("origin")
        if origin_el is not None:
            self.lines[(*key, "origin")] = origin_el.sourceline or 0
        actuation_el = element.find("actuation")
        actuation = None
        if actuation_el is not None:
            actuation = self.actuation(actuation_el, name)
        return Bendable(
            name=name,
            parent=parent.get("link"),
            child=child.get("link"),
            model=model,
            origin=self.origin(element.find("origin")),
            inertial=inertial,
            actuation=actuation,
            line=line,
        )

    def model(self, element: etree._Element, bendable: str) -> ModelSpec | None:
        key = ("bendable", bendable)
        owner = f"bendable {bendable!r}: <model>"
        self.lines[(*key, "model")] = element.sourceline or 0
        limits_el = self._once(element, "limits", owner)
        backbone_el = self._once(element, "backbone", owner)
        params: dict[str, float | str] = {}
        for p in element.findall("param"):
            pname = p.get("name")
            if pname in params:
                self.error(p, f"{owner} parameter {pname!r} given twice")
                continue
            params[pname] = _number_or_text(p.get("value"))
            self.lines[(*key, "param", pname)] = p.sourceline or 0
        missing = [t for t, el in (("limits", limits_el), ("backbone", backbone_el)) if el is None]
        for tag in missing:
            self.error(element, f"{owner} has no <{tag}> (required)")
        if missing:
            return None
        self.lines[(*key, "limits")] = limits_el.sourceline or 0
        self.lines[(*key, "backbone")] = backbone_el.sourceline or 0
        known = {"kappa_max", "kappa_rate_max", "phi_min", "phi_max"}
        extra: dict[str, float] = {}
        for attr, value in limits_el.attrib.items():
            if attr in known:
                continue
            if attr.startswith("{"):
                self.error(
                    limits_el, f"{owner}: namespaced attribute {attr!r} not allowed in <limits>"
                )
                continue
            try:
                extra[attr] = _float(value)
            except ValueError:
                self.error(limits_el, f"{owner}: <limits {attr}={shown(value)}> is not a number")
        rate = limits_el.get("kappa_rate_max")
        limits = CurvatureLimits(
            kappa_max=_float(limits_el.get("kappa_max")),
            kappa_rate_max=_float(rate) if rate is not None else None,
            phi_min=_float(limits_el.get("phi_min", repr(-math.pi))),
            phi_max=_float(limits_el.get("phi_max", repr(math.pi))),
            extra=extra,
        )
        e = backbone_el.get("youngs_modulus")
        ei = backbone_el.get("bending_stiffness")
        backbone = Backbone(
            length=_float(backbone_el.get("length")),
            radius=_float(backbone_el.get("radius", "0")),
            youngs_modulus=_float(e) if e is not None else None,
            bending_stiffness=_float(ei) if ei is not None else None,
        )
        return ModelSpec(type=element.get("type"), limits=limits, backbone=backbone, params=params)

    def actuation(self, element: etree._Element, bendable: str) -> Actuation | None:
        """The bendable's ``<actuation>``; None when its ``count`` is unusable (reported)."""
        key = ("bendable", bendable)
        owner = f"bendable {bendable!r}: <actuation>"
        self.lines[(*key, "actuation")] = element.sourceline or 0
        count = self.whole(element, "count", f"bendable {bendable!r}:")
        if count is None:  # reported; the tendons and servos cannot be judged against it
            return None
        tendons: dict[int, float] = {}
        servos: dict[int, Servo] = {}
        uarts: dict[str, dict[str, int]] = {}
        pwm_pins: dict[int, int] = {}
        pulse: PwmPulse | None = None
        #: servo index -> (min_angle given, max_angle given): the rest default below
        given: dict[int, tuple[bool, bool]] = {}
        for child in _children(element):
            if child.tag == "uart":
                self._uart(child, owner, key, uarts)
                continue
            if child.tag == "pwm_pulse":
                if pulse is not None:
                    self.error(child, f"{owner} has two <pwm_pulse>")
                    continue
                self.lines[(*key, "pwm_pulse")] = child.sourceline or 0
                pulse = PwmPulse(
                    min_us=_float(child.get("min_us", repr(PwmPulse.min_us))),
                    max_us=_float(child.get("max_us", repr(PwmPulse.max_us))),
                    range=_float(child.get("range", repr(PwmPulse.range))),
                )
                continue
            index = self.whole(child, "index", owner)
            if index is None:
                if child.tag == "servo":  # reported: not again as a missing servo
                    self.lines[(*key, "servo_reported")] = child.sourceline or 0
                continue
            if child.tag == "pwm":
                if index in pwm_pins:
                    self.error(child, f"{owner} has two <pwm> with index {index}")
                elif index >= count:
                    self.error(
                        child, f"{owner} <pwm index={index}> is out of range: count is {count}"
                    )
                elif (pin := self.whole(child, "pin", owner)) is not None:
                    self.lines[(*key, "pwm", index)] = child.sourceline or 0
                    pwm_pins[index] = pin
                continue
            table = tendons if child.tag == "tendon" else servos
            if child.tag == "servo" and (index in table or index >= count):
                # reported here: the servo-per-tendon count check must not repeat it
                self.lines[(*key, "servo_reported")] = child.sourceline or 0
            if index in table:
                self.error(child, f"{owner} has two <{child.tag}> with index {index}")
                continue
            if index >= count:
                self.error(
                    child,
                    f"{owner} <{child.tag} index={index}> is out of range: count is {count}, "
                    f"indices run 0..{count - 1}",
                )
                continue
            self.lines[(*key, child.tag, index)] = child.sourceline or 0
            if child.tag == "tendon":
                tendons[index] = _float(child.get("angle"))
                continue
            servo_id = self.whole(child, "id", owner)
            direction = self.whole(child, "direction", owner, "1")
            if servo_id is None or direction is None:
                self.lines[(*key, "servo_reported")] = child.sourceline or 0
                continue
            servos[index] = Servo(
                id=servo_id,
                zero_offset=_float(child.get("zero_offset", "0")),
                direction=direction,
                min_angle=_float(child.get("min_angle", repr(-math.pi))),
                max_angle=_float(child.get("max_angle", repr(math.pi))),
            )
            given[index] = (child.get("min_angle") is not None, child.get("max_angle") is not None)
        if len(tendons) != count:
            self.error(
                element,
                f"{owner} declares count={count} but has {len(tendons)} <tendon> elements",
            )
        driver = element.get("driver", "pwm")
        if driver == "pwm":
            # a PWM servo's travel defaults to what its pulse range spans: raw angles
            # -range/2..range/2 around the centre pulse, i.e. relative to zero_offset
            half = (pulse or PwmPulse()).half
            for i, servo in servos.items():
                has_min, has_max = given.get(i, (True, True))
                if not has_min:
                    servo.min_angle = -half - servo.zero_offset
                if not has_max:
                    servo.max_angle = half - servo.zero_offset
        return Actuation(
            type=element.get("type"),
            angles=[tendons[i] for i in sorted(tendons)],
            radius=_float(element.get("radius")),
            spool_radius=_float(element.get("spool_radius")),
            driver=element.get("driver", "pwm"),
            servos=[servos[i] for i in sorted(servos)],
            board=element.get("board"),
            uarts=uarts,
            pwm_pins=pwm_pins,
            pwm_pulse=pulse,
        )

    def _uart(
        self, child: etree._Element, owner: str, key: LineKey, uarts: dict[str, dict[str, int]]
    ) -> None:
        """``<uart role= id= tx= rx= [baud=]/>``: one UART of the segment's wiring plan."""
        role = child.get("role")
        if role in uarts:
            self.error(child, f"{owner} has two <uart role={role!r}>")
            return
        self.lines[(*key, "uart", role)] = child.sourceline or 0
        attrs = ("id", "tx", "rx", "baud") if child.get("baud") is not None else ("id", "tx", "rx")
        entry = {k: self.whole(child, k, owner) for k in attrs}
        if None not in entry.values():  # else reported
            uarts[role] = entry

    # -- ros2_control --------------------------------------------------------------------------
    def params(self, elements: list[etree._Element], owner: str, key: LineKey) -> dict[str, str]:
        out: dict[str, str] = {}
        for p in elements:
            pname = p.get("name")
            if pname in out:
                self.error(p, f"{owner}: <param name={pname!r}> given twice")
                continue
            out[pname] = (p.text or "").strip()
            self.lines[(*key, "param", pname)] = p.sourceline or 0
        return out

    def ros2_control(self, element: etree._Element, index: int) -> Ros2Control:
        key: LineKey = ("ros2_control", index)
        name = element.get("name")
        line = element.sourceline or 0
        self.lines[key] = line
        hardware = element.find("hardware")
        self.lines[(*key, "hardware")] = hardware.sourceline or 0
        control = Ros2Control(
            name=name,
            type=element.get("type", "system"),
            plugin=(hardware.findtext("plugin") or "").strip(),
            hardware_params=self.params(
                hardware.findall("param"), f"ros2_control {name!r} <hardware>", key
            ),
            line=line,
        )
        for j_index, joint_el in enumerate(element.findall("joint")):
            jname = joint_el.get("name")
            jkey = (*key, "joint", j_index)
            self.lines[jkey] = joint_el.sourceline or 0
            joint = ControlJoint(name=jname, line=joint_el.sourceline or 0)
            for iface_el in _children(joint_el):
                kind = iface_el.tag
                iname = iface_el.get("name")
                target = (
                    joint.command_interfaces
                    if kind == "command_interface"
                    else joint.state_interfaces
                )
                if any(i.name == iname for i in target):
                    self.error(
                        iface_el,
                        f"ros2_control joint {jname!r} has two <{kind} name={iname!r}>",
                    )
                    continue
                ikey = (*jkey, kind, iname)
                self.lines[ikey] = iface_el.sourceline or 0
                raw = self.params(
                    iface_el.findall("param"),
                    f"ros2_control joint {jname!r} <{kind} {iname}>",
                    ikey,
                )
                params = {
                    k: _number_or_text(v) if k in _NUMERIC_INTERFACE_PARAMS else v
                    for k, v in raw.items()
                }
                target.append(Interface(name=iname, params=params))
            control.joints.append(joint)
        return control
