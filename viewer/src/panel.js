// The weights panel: one bar per morph target, grouped under a heading per region. A key shape's
// region is the one keys.json gives it (`info.regions`: upper, lower, ...; a mirrored key stays in
// its original's region; without keys.json, read from the name: upper_03_mirror is upper's); a name
// that is not a key is "gaze" (eyeLook*, driven by the irises) or
// "targets" (a rig's own shapes). Each row shows the whole name (the name column is as wide as the
// longest) and, below it, the key's description when the take has one (`info.descriptions`).
// Bars span 0 to 1 (a weight of 1 is the sculpted shape); larger weights fill the bar in another
// colour. Clicking a name whose key shape came from this take jumps to that frame.

/** The heading a name goes under: its key's region, else "gaze" or "targets". */
export function groupOf(name, regions) {
  if (regions && regions[name]) return regions[name];
  const key = /^(.+?)_\d+(_mirror)?$/.exec(name); // keyshape's own key names: region_NN[_mirror]
  if (key) return key[1];
  return /^eyeLook/.test(name) ? 'gaze' : 'targets';
}

export class WeightsPanel {
  /**
   * @param {HTMLElement} list  the <ol> to fill
   * @param {string[]} names  morph targets, in the order `update` gets their values
   * @param {object} info  {frames: {key: frame}, regions: {key: region}, descriptions: {key: text}}
   * @param {function} onPick  called with a key's frame when its name is clicked
   */
  constructor(list, names, info, onPick) {
    const { frames = {}, regions = {}, descriptions = {} } = info || {};
    this.rows = new Array(names.length);
    const groups = new Map(); // heading -> indices of its names, in order of first appearance
    names.forEach((name, i) => {
      const group = groupOf(name, regions);
      if (!groups.has(group)) groups.set(group, []);
      groups.get(group).push(i);
    });
    for (const [group, indices] of groups) {
      const heading = document.createElement('li');
      heading.className = 'region';
      heading.textContent = group;
      list.append(heading);
      for (const i of indices) {
        const name = names[i];
        this.rows[i] = this.addRow(list, name, frames[name], descriptions[name], onPick);
      }
    }
  }

  addRow(list, name, keyFrame, description, onPick) {
    const row = document.createElement('li');
    row.className = 'weight';
    row.dataset.name = name;
    const label = document.createElement(keyFrame === undefined ? 'span' : 'button');
    label.className = 'name';
    label.textContent = name;
    label.title = description ? `${name}: ${description}` : name;
    if (keyFrame !== undefined) {
      label.title += ` (key shape from frame ${keyFrame}: click to go there)`;
      label.addEventListener('click', () => onPick(keyFrame));
    }
    const bar = document.createElement('span');
    bar.className = 'bar';
    const fill = document.createElement('span');
    fill.className = 'fill';
    bar.append(fill);
    const value = document.createElement('span');
    value.className = 'value';
    row.append(label, bar, value);
    if (description) {
      const text = document.createElement('span');
      text.className = 'description';
      text.textContent = description;
      row.append(text);
    }
    list.append(row);
    return { fill, value };
  }

  /** Show `values` (in the order of the names given). */
  update(values) {
    values.forEach((v, i) => {
      const row = this.rows[i];
      row.fill.style.width = `${(100 * Math.min(Math.max(v, 0), 1)).toFixed(1)}%`;
      row.fill.classList.toggle('over', v > 1); // past the sculpted shape: extrapolating
      row.value.textContent = v.toFixed(2);
    });
  }
}
