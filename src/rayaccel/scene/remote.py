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

from dataclasses import dataclass
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
        RemoteScene(
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
        ),
        RemoteScene(
            name="san-miguel-low-poly",
            title="San Miguel 2.1, low-poly version",
            url=f"{_MCGUIRE}/research/model/San_Miguel/San_Miguel.zip",
            sha256="85874077735808150e679b3c71d70a37a270cb8833f4911325aa1099da3f7d4a",
            size=535_519_642,
            archive="zip",
            member="san-miguel-low-poly.obj",
            licence="research and educational use with attribution (the archive's license.txt)",
            credit=(
                "Guillermo M. Leal Llaguno; 2017 update by Morgan McGuire, Guedis Cardenas, "
                "Michael Mara and Nicholas Hull"
            ),
            up="+y",
            source_of_hash="recorded with the same size by two public projects",
            notes="Shares the download of san-miguel.",
        ),
        RemoteScene(
            name="stanford-bunny",
            title="Stanford Bunny (bun_zipper reconstruction)",
            url=f"{_STANFORD}/pub/3Dscanrep/bunny.tar.gz",
            sha256="a5720bd96d158df403d153381b8411a727a1d73cff2f33dc9b212d6f75455b84",
            size=4_894_286,
            archive="tar",
            member="bunny/reconstruction/bun_zipper.ply",
            licence=_STANFORD_TERMS,
            credit=_STANFORD_CREDIT,
            up="+y",
            source_of_hash="recorded with the same size by several public projects",
            notes="69,451 triangles (Turk and Levoy 1994).",
        ),
        RemoteScene(
            name="stanford-dragon",
            title="Stanford Dragon (vrip reconstruction)",
            url=f"{_STANFORD}/pub/3Dscanrep/dragon/dragon_recon.tar.gz",
            sha256="74ac1d90989c9b1732edee82d57e9ce71452144cf4355f108d8c9c616d28d02f",
            size=11_197_764,
            archive="tar",
            member="dragon_recon/dragon_vrip.ply",
            licence=_STANFORD_TERMS,
            credit=_STANFORD_CREDIT,
            up="+y",
            source_of_hash="recorded with the same size by several public projects",
            notes="871,414 triangles.",
        ),
        RemoteScene(
            name="happy-buddha",
            title="Happy Buddha (vrip reconstruction)",
            url=f"{_STANFORD}/pub/3Dscanrep/happy/happy_recon.tar.gz",
            sha256="409cd294efbfd8244e15a382b95a9423f153b7776e736c9b09f19ec9d3c10ed0",
            size=14_456_495,
            archive="tar",
            member="happy_recon/happy_vrip.ply",
            licence=_STANFORD_TERMS,
            credit=_STANFORD_CREDIT,
            up="+y",
            source_of_hash="recorded with the same size by two public projects",
            notes="1,087,716 triangles.",
        ),
        RemoteScene(
            name="armadillo",
            title="Stanford Armadillo",
            url=f"{_STANFORD}/pub/3Dscanrep/armadillo/Armadillo.ply.gz",
            sha256="8b9b56cc36e66d54429b1e1e75bd89e833645bfe0dc7c1afd1205877a7356a3f",
            size=3_874_291,
            archive=None,
            member=None,
            licence=_STANFORD_TERMS,
            credit=_STANFORD_CREDIT,
            up="+y",
            source_of_hash="recorded with the same size by two public projects",
            notes="345,944 triangles; read gzipped as it is.",
        ),
        RemoteScene(
            name="lucy",
            title="Lucy",
            url=f"{_STANFORD}/data/3Dscanrep/lucy.tar.gz",
            sha256="c4beb1f7bfa965643bbbf889bd1849a4b4b955e95c731941be61e6edac65616a",
            size=None,
            archive="tar",
            member="lucy.ply",
            licence=_STANFORD_TERMS,
            credit=_STANFORD_CREDIT,
            source_of_hash="recorded by two public projects (download about 307 MB)",
            notes="About 28M triangles.",
        ),
        RemoteScene(
            name="xyzrgb-dragon",
            title="Asian Dragon (XYZ RGB)",
            url=f"{_STANFORD}/data/3Dscanrep/xyzrgb/xyzrgb_dragon.ply.gz",
            sha256="8aa449f1966cbb50e5896ecc32cf57ab5f0cdfd3c3e37d3e6f60b948997da5c1",
            size=70_527_166,
            archive=None,
            member=None,
            licence=_STANFORD_TERMS,
            credit=_XYZRGB_CREDIT,
            source_of_hash="recorded with the same size by two public projects",
            notes="7,219,045 triangles; read gzipped as it is.",
        ),
        RemoteScene(
            name="thai-statuette",
            title="Thai Statuette (XYZ RGB)",
            url=f"{_STANFORD}/data/3Dscanrep/xyzrgb/xyzrgb_statuette.ply.gz",
            sha256="1d867b6540c02935caa777bd6746429a62d4a5d23f11c9bfdfebbaa90c05ca8b",
            size=106_051_627,
            archive=None,
            member=None,
            licence=_STANFORD_TERMS,
            credit=_XYZRGB_CREDIT,
            source_of_hash="recorded with the same size by two public projects",
            notes="10,000,000 triangles; read gzipped as it is.",
        ),
        RemoteScene(
            name="staircase",
            title="The Wooden Staircase",
            url=f"{_BITTERLI}/staircase.zip",
            sha256=None,
            size=None,
            archive="zip",
            member="*models/*.ply",
            licence="CC BY 3.0",
            credit="Wig42 (blendswap.com/blends/view/77668); pbrt version by Benedikt Bitterli",
            up="+y",
            notes=_BITTERLI_NOTE + " All parts have identity transforms.",
        ),
        RemoteScene(
            name="living-room",
            title="The Grey & White Room",
            url=f"{_BITTERLI}/living-room.zip",
            sha256=None,
            size=None,
            archive="zip",
            member="*models/*.ply",
            licence="CC BY 3.0",
            credit="Wig42 (blendswap.com/blends/view/75795); pbrt version by Benedikt Bitterli",
            up="+y",
            notes=_BITTERLI_NOTE + " Seven parts (table and glasses) are translated in the scene.",
        ),
        RemoteScene(
            name="kitchen",
            title="Country Kitchen",
            url=f"{_BITTERLI}/kitchen.zip",
            sha256=None,
            size=None,
            archive="zip",
            member="*models/*.ply",
            licence="CC BY 3.0",
            credit=(
                "Jay-Artist (blendswap.com/blends/view/42851); pbrt version by Benedikt Bitterli"
            ),
            up="+y",
            notes=_BITTERLI_NOTE + " All parts have identity transforms.",
        ),
        RemoteScene(
            name="bathroom2",
            title="Salle de bain",
            url=f"{_BITTERLI}/bathroom2.zip",
            sha256=None,
            size=None,
            archive="zip",
            member="*models/*.ply",
            licence="CC BY 3.0",
            credit="nacimus (blendswap.com/blends/view/73937); pbrt version by Benedikt Bitterli",
            up="+y",
            notes=_BITTERLI_NOTE,
        ),
    )
}


__all__ = ["REMOTE_SCENES", "ArchiveKind", "RemoteScene"]
