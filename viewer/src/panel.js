// The weights panel: one bar per morph target, grouped by region (the name before "_").
// Bars span 0 to 1 (a weight of 1 is the sculpted shape); larger weights fill the bar in
// another colour. Clicking a name whose key shape came from this take jumps to that frame.

export class WeightsPanel {
  constructor(list, names, keyFrames, onPick) {
    this.rows = [];
    let region = null;
    for (const name of names) {
      const prefix = name.includes('_') ? name.slice(0, name.lastIndexOf('_')) : '';
      if (prefix && prefix !== region) {
        region = prefix;
        const heading = document.createElement('li');
        heading.className = 'region';
        heading.textContent = prefix;
        list.append(heading);
      }
      this.rows.push(this.addRow(list, name, keyFrames[name], onPick));
    }
  }

  addRow(list, name, keyFrame, onPick) {
    const row = document.createElement('li');
    row.className = 'weight';
    row.dataset.name = name;
    const label = document.createElement(keyFrame === undefined ? 'span' : 'button');
    label.className = 'name';
    label.textContent = name;
    if (keyFrame !== undefined) {
      label.title = `key shape from frame ${keyFrame}: click to go there`;
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
    list.append(row);
    return { fill, value };
  }

  /** Show `values` (in target order). */
  update(values) {
    values.forEach((v, i) => {
      const row = this.rows[i];
      row.fill.style.width = `${(100 * Math.min(Math.max(v, 0), 1)).toFixed(1)}%`;
      row.fill.classList.toggle('over', v > 1); // past the sculpted shape: extrapolating
      row.value.textContent = v.toFixed(2);
    });
  }
}
