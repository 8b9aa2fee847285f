"""The downloadable benchmark scenes: where each comes from, its hash, licence and credit.

Each :class:`RemoteScene` names one scene that :func:`rayaccel.scenes.fetch` downloads
from its public source (McGuire's Computer Graphics Archive, the Stanford 3D Scanning
Repository, Bitterli's Rendering Resources) into the user cache. A download is checked
against the SHA-256 in :attr:`RemoteScene.sha256`; the sources publish no checksums
themselves, so each hash here is one that two or more other public projects recorded,
in agreement, for the same URL (``source_of_hash`` says so). Entries whose hash nobody
published have ``sha256=None``, and fetch refuses them unless the user asks for an
unchecked download.

``member`` is the scene file inside an archive, a path relative to the unpacked
folder (when the archive's layout differs, a unique file of that name anywhere in it
is taken), or a glob (``*models/*.ply``) whose matches are concatenated into one PLY.
Files the loader reads as they are (``.ply.gz``) have ``member=None``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

#: Archive kinds :func:`~rayaccel.scene.fetch.fetch` unpacks (``None``: a plain file).
ArchiveKind = Literal["zip", "tar"]

_MCGUIRE = "https://casual-effects.com/g3d/data10"
_STANFORD = "https://graphics.stanford.edu"
_BITTERLI = "https://benedikt-bitterli.me/resources/pbrt-v3"

_STANFORD_TERMS = (
    "Stanford 3D Scanning Repository terms: research use and free redistribution with "
    "acknowledgement; no commercial use without Stanford's permission"
)
_STANFORD_CREDIT = "Stanford University Computer Graphics Laboratory"
_XYZRGB_CREDIT = "XYZ RGB Inc., via the Stanford 3D Scanning Repository"
_BITTERLI_NOTE = (
    "pbrt-v3 version from Benedikt Bitterli's Rendering Resources. The scene is many PLY "
    "parts; fetch concatenates them as stored, without the pbrt file's per-shape "
    "transforms or its inline area-light quads."
)


@dataclass(frozen=True, slots=True)
class RemoteScene:
    """One downloadable scene.

    Attributes
    ----------
    name : str
        The name ``fetch`` and, once cached, ``rayaccel.scenes.get`` accept.
    title : str
        Human-readable name of the model.
    url : str
        Where the file or archive is downloaded from.
    sha256 : str or None
        Expected SHA-256 of the downloaded file (lower-case hex), or ``None`` when no
        published hash is known (fetch then needs ``verify=False``).
    size : int or None
        Size of the download in bytes, where recorded (informational).
    archive : {"zip", "tar"} or None
        How the download is unpacked; ``None`` for a scene file used as is.
    member : str or None
        The scene file inside the archive, or a glob of parts to concatenate.
    licence : str
        The terms the source states.
    credit : str
        Who made the model, to be credited when it is used.
    up : str
        World up axis (``"+y"``, ``"+z"`` or ``"?"``).
    source_of_hash : str
        Where ``sha256`` was found (empty when it is ``None``).
    notes : str
        Triangle counts and caveats.
    """

    name: str
    title: str
    url: str
    sha256: str | None
    size: int | None
    archive: ArchiveKind | None
    member: str | None
    licence: str
    credit: str
    up: str = "?"
    source_of_hash: str = ""
    notes: str = ""


def _stanford(
    name: str, title: str, path: str, sha256: str, size: int | None, *,
    archive: ArchiveKind | None = None, member: str | None = None,
    credit: str = _STANFORD_CREDIT, up: str = "+y",
    source_of_hash: str = "recorded with the same size by two public projects", notes: str,
) -> RemoteScene:  # fmt: skip
    """Return a scan of the Stanford 3D Scanning Repository (``path`` below its site)."""
    return RemoteScene(
        name, title, f"{_STANFORD}/{path}", sha256, size, archive, member, _STANFORD_TERMS,
        credit, up, source_of_hash, notes,
    )  # fmt: skip


def _bitterli(name: str, title: str, author: str, notes: str = "") -> RemoteScene:
    """Return a pbrt-v3 scene of Bitterli's Rendering Resources: PLY parts in a zip, no hash."""
    return RemoteScene(
        name, title, f"{_BITTERLI}/{name}.zip", None, None, "zip", "*models/*.ply", "CC BY 3.0",
        f"{author}; pbrt version by Benedikt Bitterli", "+y", "", _BITTERLI_NOTE + notes,
    )  # fmt: skip


_SAN_MIGUEL = RemoteScene(
    name="san-miguel",
    title="San Miguel 2.1",
    url=f"{_MCGUIRE}/research/model/San_Miguel/San_Miguel.zip",
    sha256="85874077735808150e679b3c71d70a37a270cb8833f4911325aa1099da3f7d4a",
    size=535_519_642,
    archive="zip",
    member="san-miguel.obj",
    licence="research and educational use with attribution (the archive's license.txt)",
    credit=(
        "Guillermo M. Leal Llaguno; 2017 update by Morgan McGuire, Guedis Cardenas, "
        "Michael Mara and Nicholas Hull"
    ),
    up="+y",
    source_of_hash="recorded with the same size by two public projects",
    notes="About 10M triangles; the whole archive (textures included) is unpacked.",
)

REMOTE_SCENES: dict[str, RemoteScene] = {
    scene.name: scene
    for scene in (
        RemoteScene(
            name="crytek-sponza",
            title="Crytek Sponza (McGuire's cleaned OBJ)",
            url=f"{_MCGUIRE}/common/model/crytek_sponza/sponza.zip",
            sha256="da005cbee0be2df2abc8513f3ceb61bcb6f69aac112babcd9c00169a27c2770c",
            size=None,
            archive="zip",
            member="sponza.obj",
            licence="CC BY 3.0",
            credit="Frank Meinl, Crytek (2010), after Marko Dabrovic; archive by Morgan McGuire",
            up="+y",
            source_of_hash="recorded by several public projects for this URL (version 2016-06-28)",
            notes="262,267 triangles (McGuire's count); textures are unpacked but not used.",
        ),
        RemoteScene(
            name="dabrovic-sponza",
            title="Sponza Atrium, Marko Dabrovic's original (McGuire's OBJ)",
            url=f"{_MCGUIRE}/research/model/dabrovic_sponza/sponza.zip",
            sha256=None,
            size=None,
            archive="zip",
            member="sponza.obj",
            licence="free for research use with credit (see the archive's notes)",
            credit="Marko Dabrovic (RNA studio); archive by Morgan McGuire",
            up="+y",
            notes="The bundled sponza_dabrovic.ply is the same model from another source.",
        ),
        _SAN_MIGUEL,
        replace(
            _SAN_MIGUEL,
            name="san-miguel-low-poly",
            title="San Miguel 2.1, low-poly version",
            member="san-miguel-low-poly.obj",
            notes="Shares the download of san-miguel.",
        ),
        _stanford(
            "stanford-bunny", "Stanford Bunny (bun_zipper reconstruction)",
            "pub/3Dscanrep/bunny.tar.gz",
            "a5720bd96d158df403d153381b8411a727a1d73cff2f33dc9b212d6f75455b84", 4_894_286,
            archive="tar", member="bunny/reconstruction/bun_zipper.ply",
            source_of_hash="recorded with the same size by several public projects",
            notes="69,451 triangles (Turk and Levoy 1994).",
        ),
        _stanford(
            "stanford-dragon", "Stanford Dragon (vrip reconstruction)",
            "pub/3Dscanrep/dragon/dragon_recon.tar.gz",
            "74ac1d90989c9b1732edee82d57e9ce71452144cf4355f108d8c9c616d28d02f", 11_197_764,
            archive="tar", member="dragon_recon/dragon_vrip.ply",
            source_of_hash="recorded with the same size by several public projects",
            notes="871,414 triangles.",
        ),
        _stanford(
            "happy-buddha", "Happy Buddha (vrip reconstruction)",
            "pub/3Dscanrep/happy/happy_recon.tar.gz",
            "409cd294efbfd8244e15a382b95a9423f153b7776e736c9b09f19ec9d3c10ed0", 14_456_495,
            archive="tar", member="happy_recon/happy_vrip.ply", notes="1,087,716 triangles.",
        ),
        _stanford(
            "armadillo", "Stanford Armadillo", "pub/3Dscanrep/armadillo/Armadillo.ply.gz",
            "8b9b56cc36e66d54429b1e1e75bd89e833645bfe0dc7c1afd1205877a7356a3f", 3_874_291,
            notes="345,944 triangles; read gzipped as it is.",
        ),
        _stanford(
            "lucy", "Lucy", "data/3Dscanrep/lucy.tar.gz",
            "c4beb1f7bfa965643bbbf889bd1849a4b4b955e95c731941be61e6edac65616a", None,
            archive="tar", member="lucy.ply", up="?",
            source_of_hash="recorded by two public projects (download about 307 MB)",
            notes="About 28M triangles.",
        ),
        _stanford(
            "xyzrgb-dragon", "Asian Dragon (XYZ RGB)", "data/3Dscanrep/xyzrgb/xyzrgb_dragon.ply.gz",
            "8aa449f1966cbb50e5896ecc32cf57ab5f0cdfd3c3e37d3e6f60b948997da5c1", 70_527_166,
            credit=_XYZRGB_CREDIT, up="?",
            notes="7,219,045 triangles; read gzipped as it is.",
        ),
        _stanford(
            "thai-statuette", "Thai Statuette (XYZ RGB)",
            "data/3Dscanrep/xyzrgb/xyzrgb_statuette.ply.gz",
            "1d867b6540c02935caa777bd6746429a62d4a5d23f11c9bfdfebbaa90c05ca8b", 106_051_627,
            credit=_XYZRGB_CREDIT, up="?",
            notes="10,000,000 triangles; read gzipped as it is.",
        ),
        _bitterli(
            "staircase", "The Wooden Staircase", "Wig42 (blendswap.com/blends/view/77668)",
            " All parts have identity transforms.",
        ),
        _bitterli(
            "living-room", "The Grey & White Room", "Wig42 (blendswap.com/blends/view/75795)",
            " Seven parts (table and glasses) are translated in the scene.",
        ),
        _bitterli(
            "kitchen", "Country Kitchen", "Jay-Artist (blendswap.com/blends/view/42851)",
            " All parts have identity transforms.",
        ),
        _bitterli("bathroom2", "Salle de bain", "nacimus (blendswap.com/blends/view/73937)"),
    )
}


__all__ = ["REMOTE_SCENES", "ArchiveKind", "RemoteScene"]
