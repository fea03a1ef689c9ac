"""The project's own manifest, data_manifest.yaml: the committed reference set, the shipped generator
checkpoint and the recipe it was trained with, derived from the files. ``scenegen manifest
refresh`` rewrites those entries (atomically), keeping every other source (batches
added with ``scenegen manifest add``), the datasheet and the transfer section as they are, and
exports the JSON Schema to docs/manifest.schema.json."""

from __future__ import annotations

import json
from pathlib import Path

from scenegen.manifest.derive import checkpoint_ref, effective_shares
from scenegen.manifest.io import read_manifest, write_manifest
from scenegen.manifest.schema import (
    Datasheet,
    Manifest,
    ModelEntry,
    RecipeComponent,
    TrainingRecipe,
    TransferOutcome,
)
from scenegen.paths import PROJECT_ROOT
from scenegen.store.batch import atomic_write

MANIFEST = PROJECT_ROOT / "data_manifest.yaml"
REFERENCE = PROJECT_ROOT / "assets" / "reference" / "reference.parquet"
GENERATOR = "assets/generator"

DATASHEET = Datasheet(
    intended_use=(
        "Training and evaluating recovery policies and scene generators for tabletop manipulation with a "
        "Panda arm, where real data barely covers rare cases (near_edge, under_overhang, toppled, occluded, "
        "clutter, stacked, low_light, on_floor): synthetic scenes are mixed with real (here: reference) "
        "data at a recorded weight alpha."
    ),
    known_limitations=[
        "No real data yet: the 'reference' source is procedural and stands in for real tabletop data; "
        "every realism figure is measured against it, not against the real world.",
        "12 primitive-built object assets in 9 categories; one table, shelf and bin; one robot (Panda).",
        "Rare-case tags are geometric predicates on the settled scene (docs/tags.md), not human labels.",
        "Renders are MuJoCo OpenGL (Mesa on CPU): no textures of real objects, simple lighting.",
        "The generator's null-condition distribution is measurably off the reference (docs/generator.md: "
        "C2ST 0.610 on 2,000 scenes; under_overhang, toppled and clutter rates outside tolerance).",
    ],
    out_of_scope=[
        "Claims about real-world transfer: the transfer outcome is measured on a simulated panel (held-out "
        "reference layouts), never on a real robot or real rare cases.",
    ],
)
TRANSFER = TransferOutcome(
    status="pending",
    panel="simulated",
    note=(
        "Not measured yet. The evaluation panel will be simulated stand-ins for real rare cases: fixed, "
        "committed held-out layout ids of the reference set (DESIGN.md, 'The consumers')."
    ),
)


def generator_recipe(reference_counts) -> TrainingRecipe:
    """The recipe the shipped generator was trained with: the reference set's train split, rare
    layouts oversampled (assets/generator/config.json ``train``); no synthetic data (alpha 0)."""
    train = json.loads((PROJECT_ROOT / GENERATOR / "config.json").read_text())["train"]
    components = [RecipeComponent(source="reference", role="real", split=train["split"])]
    sizes = {"reference": reference_counts.splits[train["split"]]}
    return TrainingRecipe(
        name="generator",
        purpose="the diffusion generator's denoiser (scenegen train)",
        alpha=0.0,
        components=components,
        effective_shares=effective_shares(0.0, components, sizes),
        rebalance={"rare_share": train["rare_share"], "p_null": train["p_null"]},
    )


def project_manifest(existing: Manifest | None = None) -> Manifest:
    """data_manifest.yaml's derived entries, with ``existing``'s other sources, datasheet and transfer."""
    from scenegen.data.reference import reference_source

    reference = reference_source(REFERENCE, PROJECT_ROOT)
    recipe = generator_recipe(reference.counts)
    config = json.loads((PROJECT_ROOT / GENERATOR / "config.json").read_text())
    model = ModelEntry(
        name="generator",
        kind="diffusion_generator",
        checkpoint=checkpoint_ref(GENERATOR),
        recipe=recipe.name,
        steps=config["step"],
    )
    others = [s for s in existing.sources if s.name != "reference"] if existing else []
    return Manifest(
        kind="project",
        datasheet=existing.datasheet if existing else DATASHEET,
        sources=[reference, *others],
        models=[model, *([m for m in existing.models if m.name != "generator"] if existing else [])],
        recipes=[recipe, *([r for r in existing.recipes if r.name != "generator"] if existing else [])],
        transfer=existing.transfer if existing else TRANSFER,
    )


def write_json_schema(out: Path = PROJECT_ROOT / "docs" / "manifest.schema.json") -> None:
    """Export the manifest's JSON Schema (docs/manifest.schema.json)."""
    atomic_write(out, json.dumps(Manifest.model_json_schema(), indent=1) + "\n")


def refresh(path: Path = MANIFEST) -> Path:
    """Re-derive a project manifest's entries from the files (``scenegen manifest refresh``), keeping
    its other sources, datasheet and transfer section, and re-export the JSON Schema. A missing
    manifest is written anew; an invalid one is an error (ManifestError), so nothing of it is lost."""
    write_json_schema()
    existing = read_manifest(path) if Path(path).exists() else None
    write_manifest(path, project_manifest(existing))
    return Path(path)
