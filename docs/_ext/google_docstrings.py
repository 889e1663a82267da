"""A docutils parser for sphinx-autodoc2: Google-style docstrings -> reStructuredText.

sphinx-autodoc2 analyses the source statically and parses each docstring with the parser named
in ``autodoc2_docstring_parser_regexes`` (``get_parser_class`` imports a module and takes its
``Parser``). This module's :class:`Parser` runs Sphinx's own napoleon converter
(``sphinx.ext.napoleon.docstring.GoogleDocstring``) on the docstring first, then parses the
result as reStructuredText, so the project's Google-style sections (``Args:``, ``Returns:``,
``Raises:``, ``Attributes:``, ``Example:``, and the custom ``Options:``) render as field lists.
"""

from __future__ import annotations

from docutils import nodes
from docutils.parsers.rst import Parser as RSTParser
from sphinx.ext.napoleon import Config as NapoleonConfig
from sphinx.ext.napoleon.docstring import GoogleDocstring
from sphinx.util.docutils import LoggingReporter

__all__ = ["Parser", "NAPOLEON_SETTINGS", "google_to_rst"]

NAPOLEON_SETTINGS = dict(
    napoleon_google_docstring=True,
    napoleon_numpy_docstring=False,
    # ``:ivar:`` fields, not ``.. attribute::`` directives: autodoc2 already documents the
    # attributes of classes and dataclasses as objects, and a second description of the same
    # object would be a duplicate-object warning
    napoleon_use_ivar=True,
    napoleon_use_param=True,
    napoleon_use_rtype=False,
    napoleon_use_admonition_for_examples=False,
    napoleon_use_admonition_for_notes=True,
    napoleon_preprocess_types=False,
    napoleon_attr_annotations=False,
    # materials and effects document their constructor options in an ``Options:`` section;
    # toolkit.synthetic.SceneSpec groups its fields under the other headings
    napoleon_custom_sections=[
        ("Options", "params_style"),
        ("Object", "params_style"),
        ("Physics", "params_style"),
        ("Video and cameras", "params_style"),
        ("Truth resolution", "params_style"),
        ("Misc", "params_style"),
    ],
)

_CONFIG = NapoleonConfig(**NAPOLEON_SETTINGS)


def google_to_rst(docstring: str) -> str:
    """The reStructuredText that napoleon makes of a Google-style docstring."""
    return str(GoogleDocstring(docstring, _CONFIG))


class Parser(RSTParser):
    """reStructuredText parser that converts Google-style sections first.

    autodoc2 parses each docstring into a scratch document whose reporter is docutils' own, which
    prints markup problems to stderr without Sphinx counting them. Here the reporter is swapped for
    Sphinx's :class:`~sphinx.util.docutils.LoggingReporter`, so a malformed docstring is a build
    warning (an error under ``-W``) located at its source file and line.
    """

    supported = ("google",)

    def parse(self, inputstring: str, document: nodes.document) -> None:
        old = document.reporter
        reporter = LoggingReporter(
            document.get("source", ""), old.report_level, old.halt_level, old.debug_flag, old.error_handler
        )
        # autodoc2 maps line numbers to the docstring's source file on the reporter it made
        reporter.get_source_and_line = old.get_source_and_line
        document.reporter = reporter
        try:
            super().parse(google_to_rst(inputstring), document)
        finally:
            document.reporter = old
